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

from fieldcal.goniometer import method as gon  # noqa: E402
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
    frames = gon.read_frames_csv(folder / "frames.csv")
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


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--markdown", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.workdir or Path(tmp)
        lines = ["## Goniometer method on synthetic sessions (bench/bench_goniometer.py)", ""]
        for name in ("canon5d2", "h3d"):
            lines += run(name, workdir, args.scale, args.seed)
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")


if __name__ == "__main__":
    main()
