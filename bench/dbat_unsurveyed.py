"""The DBAT calibration sheet with only its four control points (issue 26, goal 6; marks path).

PhotoModeler's marks of the 21 photos (``../shared/data/dbat-camcal``, ``tests/realdata.py``),
the four control points 1001-1004 at the unit square's corners (``ctrlpts-weighted.txt``,
sigma 0.001 units; the sheet's units used as metres), the other 96 targets unsurveyed. Three
runs: (a) weighted control (4 points), (b) a free network without scale, (c) scaled by one side
of the square as a scale bar (1001-1002, 1 unit, sigma 0.0001 units; a minimal scale), (d) by two
sides (1001-1002 and 1003-1001; observations of the adjustment), (e) for comparison,
today's way: PhotoModeler's adjusted coordinates of all 100 targets as the survey.
fieldcal-brown/1 models the pixel aspect with ``a1, a2`` where PhotoModeler and DBAT fit a
format width.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/dbat_unsurveyed.py
"""

from __future__ import annotations

import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fieldcal.field.adjustment import AdjustmentOptions, adjust_field  # noqa: E402
from fieldcal.model.camera import INDEX  # noqa: E402
from fieldcal.session.data import ScaleBars  # noqa: E402
from tests.realdata import DBAT, dbat_field_data  # noqa: E402

CONTROL = {"1001": (0, 1, 0), "1002": (1, 1, 0), "1003": (0, 0, 0), "1004": (1, 0, 0)}


def four_control(data):
    t = data.targets
    xyz = np.full_like(t.xyz_m, np.nan)
    sigma = t.sigma_mm.copy()
    for k, tid in enumerate(t.ids):
        if tid in CONTROL:
            xyz[k] = CONTROL[tid]
            sigma[k] = 1.0                      # 0.001 units, as ctrlpts-weighted.txt
    return replace(data, targets=replace(t, xyz_m=xyz, sigma_mm=sigma))


def main():
    assert (DBAT / "ctrlpts-weighted.txt").is_file()
    print("load:", os.getloadavg())
    pm = dbat_field_data()
    data = four_control(pm)
    index = data.targets.index()
    bars = ScaleBars([index["1001"], index["1003"]], [index["1002"], index["1001"]], [1000.0, 1000.0],
                     [0.1, 0.1])
    one = ScaleBars([index["1001"]], [index["1002"]], [1000.0], [0.1])
    runs = {"4 control points, 96 unsurveyed": (data, AdjustmentOptions()),
            "free network, no scale bar": (data, AdjustmentOptions(datum="free")),
            "free network, 1 side as a scale bar": (replace(data, scale_bars=one), AdjustmentOptions(datum="free")),
            "free network, 2 sides as scale bars": (replace(data, scale_bars=bars), AdjustmentOptions(datum="free")),
            "PhotoModeler's 100 object points as survey": (pm, AdjustmentOptions())}
    print("| run | f [mm] | xp [mm] | yp [mm] | k1 [mm^-2] | sigma0 | held |")
    print("|---|---|---|---|---|---|---|")
    for name, (d, o) in runs.items():
        r = adjust_field(d, o)
        cells = [f"{r.params[INDEX[p]]:.5f} ± {r.sigma[p]:.5f}" for p in ("f_mm", "xp_mm", "yp_mm")]
        cells.append(f"{r.params[INDEX['k1']]:.4e} ± {r.sigma['k1']:.1e}")
        st = r.stats()
        held = ", ".join(st["fixed_parameters"]) or "-"
        print(f"| {name} | " + " | ".join(cells) + f" | {st['sigma0']:.3f} | {held} |")
        if "scale_bars" in r.datum:
            print("   bars:", [(b["from_id"], b["to_id"], round(b["adjusted_mm"], 3), round(b["sigma_adjusted_mm"], 3),
                            round(b["residual_mm"], 4), round(b["redundancy"], 3), b["normalized_residual"])
                           for b in r.datum["scale_bars"]])
        if "n_unsurveyed_targets" in st:
            print("   unsurveyed targets adjusted:", st["n_unsurveyed_targets"], "; a2", r.params[INDEX["a2"]],
                  "±", r.sigma.get("a2"))


if __name__ == "__main__":
    main()
