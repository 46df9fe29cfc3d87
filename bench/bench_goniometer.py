"""Benchmark: the goniometer method on full-size synthetic sessions (Canon 5D II, H3D).

Usage::

    python bench/bench_goniometer.py [--workdir DIR] [--scale S] [--markdown FILE]

For each camera: renders a full session (3 frames per angle, 16-bit tiled zstd TIFFs at the
real sensor size unless ``--scale``; the spot and its noise only in a window around it),
measures every frame as the flow would (read + spot), calibrates with the linearised and
the rigorous variant, and compares against the exact truth:

- timing per frame (render, read + measure) and of the solve;
- spot centroid error against the rendered positions (RMS, px);
- f and the principal point against the values of the same set-up from the exact spot
  positions (noise-free), in units of the reported sigma;
- the fit's sigma (eq. 10) against the RMS error of the 3-frame means;
- the correction along both axes against the truth, the common pointing removed (px RMS/max);
- the noise-free method error of both variants and of the paper's equations verbatim
  (``zero_offset=False``) and without the sweeps' pointing (``fit_pointing=False``).

Prints a markdown table (and writes it to ``--markdown`` if given).

``--repeat N``: repeat sessions of one unchanged camera (issue 16), per camera: N rendered
sessions at ``--scale`` (each a new seed: a new alignment on the arm, new encoder errors,
jitter and pixel noise), calibrated; the scatter of f, xp, yp across the sessions against
the reported sigmas, ``|error| / sigma`` against the method's value for the true camera
(the exact spots of a perfectly aligned set-up), and ``fieldcal compare``'s verdict on the
N/2 independent pairs; then the same for ``--pairs`` pairs of sessions simulated without
images (tests/goniometer/simulate.py).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fieldcal.analysis.compare import compare_calibrations  # noqa: E402
from fieldcal.analysis.uncertainty import Calibration  # noqa: E402
from fieldcal.goniometer import method as gon  # noqa: E402
from fieldcal.model.camera import PARAM_NAMES  # noqa: E402
from fieldcal.session.frames import read_frames_csv  # noqa: E402
from fieldcal.synthetic.goniometer import write_session  # noqa: E402

KEYS = ("f_mm", "xp_mm", "yp_mm")


def along_truth(res, camera):
    uv = np.column_stack([res.residuals["u_px"].to_numpy(), res.residuals["v_px"].to_numpy()])
    d = gon.along_axis_difference_px(res.parameters, camera.params, res.sensor, uv,
                                     np.array(res.residuals["axis"].to_pylist()))
    return float(np.sqrt(np.mean(d**2))), float(np.abs(d).max())


def run(name: str, workdir: Path, scale: float, seed: int) -> list[str]:
    folder = workdir / f"{name}-{scale:g}"
    t0 = time.perf_counter()
    truth = write_session(folder, name, seed=seed, raster_scale=scale)
    t1 = time.perf_counter()
    frames = read_frames_csv(folder / "frames.csv")
    meas = gon.measure_session(folder, frames, truth.sensor)
    t2 = time.perf_counter()
    n = frames.num_rows
    du = meas["u_px"].to_numpy() - truth.frames["u_rendered_px"].to_numpy()
    dv = meas["v_px"].to_numpy() - truth.frames["v_rendered_px"].to_numpy()
    size_kb = sum(p.stat().st_size for p in (folder / "images").iterdir()) / n / 1024
    s = truth.sensor
    out = [f"### {name}: {s.width_px} x {s.height_px} px of {s.pixel_size_um:g} um, {n} frames",
           "",
           f"- render {1e3 * (t1 - t0) / n:.0f} ms/frame ({size_kb:.0f} KB/frame on disk), "
           f"read + measure {1e3 * (t2 - t1) / n:.0f} ms/frame",
           f"- centroid error vs the rendered spot: {np.sqrt(np.mean(du**2)):.4f} px (u), "
           f"{np.sqrt(np.mean(dv**2)):.4f} px (v) RMS",
           "",
           "| variant | solve [s] | f [mm] | z(f) | z(xp) | z(yp) | sigma_fit [px] | 3-frame mean error [px] "
           "| along axes vs truth RMS / max [px] | noise-free: RMS / max [px] |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    exact = truth.exact_measurements()
    for label, kw in [("linearised (eq. 5')", {}), ("rigorous (eq. 2')", {"rigorous": True}),
                      ("paper verbatim (eq. 5)", {"zero_offset": False}),
                      ("without sweep pointing", {"fit_pointing": False})]:
        t3 = time.perf_counter()
        res = gon.calibrate(s, frames, meas, **kw)
        t4 = time.perf_counter()
        ref = gon.calibrate(s, frames, exact, **kw)
        z = [(res.parameters[i] - ref.parameters[i]) / res.sigma[k] for i, k in enumerate(KEYS)]
        # the 3-frame means' error along the sweep
        t = {(a, w): (u, v) for a, w, u, v in zip(*(truth.frames[c].to_pylist()
                                                    for c in ("axis", "angle_deg", "u_px", "v_px")), strict=True)}
        r = res.residuals
        e = [u - t[a, w][0] if a == "x" else t[a, w][1] - v
             for a, w, u, v in zip(*(r[c].to_pylist() for c in ("axis", "angle_deg", "u_px", "v_px")), strict=True)]
        rms_mean = float(np.sqrt(np.mean(np.square(e))))
        a_rms, a_max = along_truth(res, truth.camera)
        n_rms, n_max = along_truth(ref, truth.camera)
        out.append(f"| {label} | {t4 - t3:.2f} | {res.parameters[0]:.5f} +- {res.sigma['f_mm']:.5f} | "
                   f"{z[0]:+.2f} | {z[1]:+.2f} | {z[2]:+.2f} | {res.stats['sigma_fit_px']:.4f} | "
                   f"{rms_mean:.4f} | {a_rms:.4f} / {a_max:.4f} | {n_rms:.4f} / {n_max:.4f} |")
        if label.startswith("linearised"):
            summary = res.report_lines()
    out += ["", "```", *summary, "```", ""]
    return out


def _calibration(res, label: str) -> Calibration:
    doc = dict(res.document_fields(), version=label, camera_id="c", session_id=label)
    return Calibration.from_document(doc, PARAM_NAMES, res.covariance)


def _repeat_row(label: str, cals: list, conv: np.ndarray) -> str:
    P = np.array([c.camera.params[:3] for c in cals])
    S = np.array([[c.sigma_of(k) for k in KEYS] for c in cals])
    scatter = P.std(axis=0, ddof=1) / np.sqrt(np.mean(S**2, axis=0))
    z = np.sqrt(np.mean(((P - conv) / S) ** 2, axis=0))
    comps = [compare_calibrations(cals[2 * i], cals[2 * i + 1]) for i in range(len(cals) // 2)]
    p = np.array([c.p_value for c in comps])
    per = np.array([[t.p_value for t in c.tests] for c in comps])
    return (f"| {label} | {len(cals)} | " + " / ".join(f"{x:.2f}" for x in scatter) + " | "
            + " / ".join(f"{x:.2f}" for x in z) + f" | {len(comps)} | {(p < 0.01).sum()} | "
            f"{(p < 0.05).sum()} | " + " / ".join(f"{x:.2f}" for x in (per < 0.05).mean(axis=0)) + " |")


def repeat(name: str, workdir: Path, scale: float, n: int, pairs: int) -> list[str]:
    """Repeat sessions of one camera (module docstring, ``--repeat``)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.goniometer.simulate import simulated_session

    rendered, t0 = [], time.perf_counter()
    for seed in range(n):
        folder = workdir / f"{name}-repeat-{seed}"
        truth = write_session(folder, name, seed=100 + seed, raster_scale=scale)
        frames = read_frames_csv(folder / "frames.csv")
        meas = gon.measure_session(folder, frames, truth.sensor)
        rendered.append(_calibration(gon.calibrate(truth.sensor, frames, meas), f"r{seed}"))
    t1 = time.perf_counter()
    simulated = []
    for k in range(2 * pairs):
        cam, frames, meas = simulated_session(name, seed=5000 + k, raster_scale=scale)
        simulated.append(_calibration(gon.calibrate(cam.sensor, frames, meas), f"s{k}"))
    t2 = time.perf_counter()
    aligned = {a: {"zero_px": [0.0, 0.0], "tilt_mrad": 0.0, "cone_mrad": 0.0} for a in "xy"}
    exact = write_session(workdir / f"{name}-aligned", name, seed=0, raster_scale=scale,
                          misalignment=aligned, noise=False, jitter_px=0.0, encoder_sigma_arcsec=0.0)
    f_exact = read_frames_csv(exact.folder / "frames.csv")
    conv = gon.calibrate(exact.sensor, f_exact, exact.exact_measurements()).parameters[:3]
    s = exact.sensor
    return [f"### {name}: repeat sessions of one camera ({s.width_px} x {s.height_px} px of "
            f"{s.pixel_size_um:g} um)", "",
            f"rendered: {(t1 - t0) / max(n, 1):.1f} s per session (render, measure, calibrate); "
            f"simulated (no images): {(t2 - t1) / max(2 * pairs, 1):.2f} s per session", "",
            "| sessions | n | scatter / sigma: f / xp / yp | RMS abs(error) / sigma: f / xp / yp | pairs "
            "| significant at 0.01 | at 0.05 | per-test rate at 0.05: f / pp / edge / map |",
            "|---|---|---|---|---|---|---|---|",
            _repeat_row("rendered", rendered, conv), _repeat_row("simulated", simulated, conv), ""]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--repeat", type=int, default=0, help="repeat sessions per camera (issue 16)")
    ap.add_argument("--pairs", type=int, default=100, help="with --repeat: simulated pairs")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.workdir or Path(tmp)
        lines = ["## Goniometer method on synthetic sessions (bench/bench_goniometer.py)", ""]
        for name in ("canon5d2", "h3d"):
            lines += (repeat(name, workdir, args.scale, args.repeat, args.pairs) if args.repeat
                      else run(name, workdir, args.scale, args.seed))
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")


if __name__ == "__main__":
    main()
