"""Figures of issue 6 (reports, exports): export fits and round trips, undistortion and report
timing at real sizes, and a laboratory-versus-field comparison of one camera.

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_reports.py [--lab-vs-field]``.
Results are copied into ``bench/README_reports.md``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from fieldcal import pipeline
from fieldcal.analysis.compare import compare_calibrations
from fieldcal.analysis.uncertainty import Calibration
from fieldcal.lake.store import Lake
from fieldcal.model.camera import INDEX, Camera, Sensor
from fieldcal.products.export import fit_metashape, fit_opencv
from fieldcal.products.report import write_report
from fieldcal.products.undistort import undistort_image
from fieldcal.synthetic.field import IXU150_TABLE1, WIDE_ANGLE, paper_field
from fieldcal.synthetic.goniometer import make_scenario, write_session
from fieldcal.synthetic.session_writer import write_field_session

CAMERAS = {
    "iXU150 (paper Table 1), 8208 x 6280": Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1),
    "wide 24 mm, 6000 x 4000": Camera.from_dict(Sensor(6000, 4000, 3.9), WIDE_ANGLE),
    "Canon 5D II 24 mm (lab), 5616 x 3744": make_scenario("canon5d2").camera(),
    "Hasselblad H3D 50 mm (lab), 7216 x 5412": make_scenario("h3d").camera(),
}


def exports() -> None:
    print("| camera | target model | fit max [px] | fit RMS [px] | round trip max [px] | exact |")
    print("|---|---|---|---|---|---|")
    for name, cam in CAMERAS.items():
        for model in ("brown4", "brown5", "rational8", "prism12"):
            t = time.perf_counter()
            f = fit_opencv(cam, model)
            dt = time.perf_counter() - t
            print(f"| {name} | OpenCV {model} ({dt:.1f} s) | {f.fit_max_px:.4f} | {f.fit_rms_px:.4f} | "
                  f"{f.roundtrip_max_px:.4f} | {'yes' if f.exact else 'no'} |")
        f = fit_metashape(cam)
        print(f"| {name} | Metashape frame | {f.fit_max_px:.4f} | {f.fit_rms_px:.4f} | "
              f"{f.roundtrip_max_px:.4f} | {'yes' if f.exact else 'no'} |")


def undistort_timing() -> None:
    cam = CAMERAS["iXU150 (paper Table 1), 8208 x 6280"]
    img = np.random.default_rng(0).integers(0, 65535, (6280, 8208), dtype=np.uint16)
    t = time.perf_counter()
    undistort_image(img, cam)
    print(f"undistort 8208 x 6280 uint16, bilinear: {time.perf_counter() - t:.1f} s")


def report_timing(root: Path) -> None:
    sf = paper_field(seed=0)
    write_field_session(root / "s", sf, images=False, observations_csv=True, camera_id="ixu150")
    p = pipeline.prepare(root / "s")
    out = pipeline.solve(p, {}, fingerprint_=pipeline.input_fingerprint(p, {}))
    lake = Lake(root / "lake")
    v = lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs)
    t = time.perf_counter()
    files = write_report(lake, v, root / "report")
    print(f"report of the paper's field (72 images, {out.document['stats']['n_observations']} points): "
          f"{time.perf_counter() - t:.1f} s, {files.html.stat().st_size / 1e6:.1f} MB HTML")
    cal = Calibration.from_lake(lake, v)
    for model in ("brown5", "prism12"):
        f = fit_opencv(cal.camera, model)
        print(f"estimated camera (a1 {'fixed' if 'a1' not in cal.names else 'estimated'}): OpenCV "
              f"{model}: fit max {f.fit_max_px:.4f} px, round trip max {f.roundtrip_max_px:.4f} px")


def lab_vs_field(root: Path) -> None:
    """The Hasselblad scenario (4x coarser raster) calibrated on the goniometer and in the field."""
    sc = make_scenario("h3d", raster_scale=0.25)
    cam = sc.camera()
    lake = Lake(root / "lake2")
    sf = paper_field(seed=3, n_attitudes=6, camera=cam)
    write_field_session(root / "f", sf, images=False, observations_csv=True, camera_id="h3d",
                        nominal_focal_mm=50.0)
    p = pipeline.prepare(root / "f")
    out = pipeline.solve(p, {}, fingerprint_=pipeline.input_fingerprint(p, {}))
    vf = lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs)
    write_session(root / "g", "h3d", seed=1, raster_scale=0.25, frames_per_angle=2, camera_id="h3d")
    p = pipeline.prepare(root / "g")
    meas = {n: pipeline.measure(p, n) for n in p.to_measure}
    out = pipeline.solve(p, meas, fingerprint_=pipeline.input_fingerprint(
        p, {n: pipeline.image_hash(p, n) for n in p.to_measure}))
    vg = lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs)
    field, lab = Calibration.from_lake(lake, vf), Calibration.from_lake(lake, vg)
    truth = Calibration(lab.document, cam, (), np.zeros((0, 0)))
    for a, b, label in ((lab, field, "lab vs field"), (truth, field, "truth vs field"),
                        (truth, lab, "truth vs lab")):
        c = compare_calibrations(a, b)
        print(f"{label}: chi2 {c.chi2:.1f} ({c.dof} dof), p {c.p_value:.2g}; {c.verdict}")
    for n in lab.names:
        i = lab.names.index(n)
        j = INDEX[n]
        print(f"  lab {n}: {(lab.camera.params[j] - cam.params[j]) / np.sqrt(lab.covariance[i, i]):+.1f} "
              "sigma from the truth")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lab-vs-field", action="store_true", help="also the lab/field comparison (~40 s)")
    args = ap.parse_args()
    exports()
    undistort_timing()
    with tempfile.TemporaryDirectory() as tmp:
        report_timing(Path(tmp))
        if args.lab_vs_field:
            lab_vs_field(Path(tmp))


if __name__ == "__main__":
    main()
