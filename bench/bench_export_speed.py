"""How long an OpenCV export takes: the fit as it was (finite differences, up to 5000 evaluations
per Lawson round) against now (analytic Jacobian, 100), on the same cameras in one run (issue 30).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_export_speed.py

The goniometer camera is what ``fieldcal synth`` (canon5d2, seed 0) and the method give: f with
k0 = -0.0154, the case that took 41 s; the others are the field scenarios' true cameras. CPU
time of ``fit_opencv(camera, "auto")`` (what ``fieldcal export --format opencv`` runs), the
model chosen and its round trip.
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from fieldcal.model.camera import Camera, Sensor  # noqa: E402
from fieldcal.products import export  # noqa: E402
from fieldcal.synthetic.field import IXU150_TABLE1, WIDE_ANGLE  # noqa: E402
from fieldcal.synthetic.goniometer import make_scenario  # noqa: E402

GONIOMETER = {"f_mm": 23.93576281, "xp_mm": 0.07125548, "yp_mm": -0.04130444, "k0": -0.01538823,
              "k1": 0.00010914, "k2": -7.492787e-08, "k3": 4.64189e-11, "p1": 8.662534e-06,
              "p2": -4.755031e-06, "b1": 2.80367e-05}
CAMERAS = {
    "goniometer calibration, canon5d2 (k0 -0.0154)": Camera.from_dict(
        make_scenario("canon5d2", raster_scale=0.25).camera().sensor, GONIOMETER),
    "iXU150 (paper Table 1)": Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1),
    "wide 24 mm": Camera.from_dict(Sensor(6000, 4000, 3.9), WIDE_ANGLE),
}


def _as_before(fn):
    """The fit of before: no Jacobian (SciPy's finite differences), 5000 evaluations a round."""
    def fit(project, x0, n, uv, *, rounds=25, jacobian=None):
        return fn(project, x0, n, uv, rounds=rounds, jacobian=None)
    return fit


def main() -> None:
    now_fit, now_nfev = export._minimax_fit, export.MAX_NFEV
    print("| camera | fit | CPU [s] | model chosen | round trip max [px] |")
    print("|---|---|---|---|---|")
    for name, cam in CAMERAS.items():
        cpu = {}
        for label in ("before", "now"):
            export._minimax_fit = _as_before(now_fit) if label == "before" else now_fit
            export.MAX_NFEV = 5000 if label == "before" else now_nfev
            t = time.process_time()
            fit = export.fit_opencv(cam, "auto")
            cpu[label] = time.process_time() - t
            print(f"| {name} | {label} | {cpu[label]:.2f} | {fit.model} | {fit.roundtrip_max_px:.4f} |")
        print(f"| {name} | ratio now / before | {cpu['now'] / cpu['before']:.3f} | | |")
    export._minimax_fit, export.MAX_NFEV = now_fit, now_nfev


if __name__ == "__main__":
    main()
