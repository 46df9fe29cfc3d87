"""Loaders of the real measured data in ../shared/data (see each folder's README.md).

The data live outside the repository. ``$FIELDCAL_SHARED_DATA`` names the folder when set
(and then only it is looked at); otherwise ``../shared/data`` beside the checkout, then
``/work/shared/data``. When a data set is not there, the tests that need it skip with the
reason (:func:`require`; every loader below calls it), and the rest of the suite runs.

- ``opencv-calib1``: OpenCV's calib1.dat inputs: 7 views of a planar 7 x 5 chessboard
  (2.54 cm squares) seen by a 640 x 480 camera, corner pixels in OpenCV's convention
  (centre of the top-left pixel at (0, 0), the same as fieldcal's).
- ``dbat-camcal``: PhotoModeler's marks of a planar calibration sheet in 21 photos of an
  Olympus C-4040Z (2272 x 1704 px); PhotoModeler's pixel convention puts the centre of the
  top-left pixel at (0.5, 0.5), so 0.5 is subtracted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fieldcal.model.camera import Sensor
from fieldcal.session.data import FieldData, FieldImage, FieldObservations, TargetField


def _data_dir() -> Path:
    """``$FIELDCAL_SHARED_DATA`` when set, else ``../shared/data`` beside the checkout, else
    /work/shared/data (the first that holds a data set; the first candidate if none does)."""
    import os

    if os.environ.get("FIELDCAL_SHARED_DATA"):
        return Path(os.environ["FIELDCAL_SHARED_DATA"])
    candidates = [Path(__file__).resolve().parents[2] / "shared" / "data", Path("/work/shared/data")]
    for c in candidates:
        if (c / "opencv-calib1").is_dir():
            return c
    return candidates[0]


DATA = _data_dir()
CALIB1 = DATA / "opencv-calib1" / "calib1_inputs.dat"
DBAT = DATA / "dbat-camcal"
FILES = {"opencv-calib1": ["calib1_inputs.dat"],
         "dbat-camcal": ["images.txt", "objpts-pm.txt", "markpts.txt", "images"]}
"""What each data set must hold for its tests."""


def missing(name: str) -> str | None:
    """Why the data set ``name`` cannot be used here, or None when it is complete."""
    absent = [f for f in FILES[name] if not (DATA / name / f).exists()]
    if absent:
        return (f"real data {name} not found in {DATA} (missing {', '.join(absent)}); set "
                "FIELDCAL_SHARED_DATA to the folder holding opencv-calib1/ and dbat-camcal/")
    return None


def require(name: str) -> Path:
    """The folder of the data set ``name``; skips the calling test when it is absent."""
    reason = missing(name)
    if reason is not None:
        pytest.skip(reason)
    return DATA / name

CALIB1_PIXEL_UM = 5.0
"""calib1 gives no pixel size; any value works (f in mm = f in px times this)."""


def calib1_raw():
    """(width, height, object points (views, 35, 3) [cm], image points (views, 35, 2) [px], flags)."""
    tok = (require("opencv-calib1") / "calib1_inputs.dat").read_text().split()
    w, h, nx, ny, nviews, flags = (int(t) for t in tok[:6])
    vals = np.array(tok[6:], dtype=float)
    n = nx * ny
    obj = vals[: nviews * n * 3].reshape(nviews, n, 3)
    img = vals[nviews * n * 3: nviews * n * 3 + nviews * n * 2].reshape(nviews, n, 2)
    return w, h, obj, img, flags


def calib1_field_data(sigma_px: float = 0.1) -> FieldData:
    """calib1 as a field problem: the board's corners as surveyed targets (exact, 1e-3 mm)."""
    w, h, obj, img, _ = calib1_raw()
    nviews, n = img.shape[:2]
    xyz_m = obj[0] / 100.0
    targets = TargetField(np.array([f"C{i:02d}" for i in range(n)]), xyz_m, 1e-3, -1)
    images = [FieldImage(f"images/view{v + 1}.tif", None) for v in range(nviews)]
    obs = FieldObservations(np.repeat(np.arange(nviews), n), np.tile(np.arange(n), nviews),
                            img.reshape(-1, 2), sigma_px)
    return FieldData(Sensor(w, h, CALIB1_PIXEL_UM), targets, images, obs, nominal_focal_mm=None,
                     default_sigma_px=sigma_px)


def dbat_field_data(sigma_px: float = 0.1) -> FieldData:
    """The DBAT camera-calibration sheet: PhotoModeler's marks and object points.

    Object units are the sheet's (a unit square between the control points), used as
    metres; the target sigmas are PhotoModeler's estimates converted to mm of those units.
    """
    require("dbat-camcal")
    names = {}
    for line in (DBAT / "images.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            i, path = line.split(",")
            names[int(i)] = "images/" + Path(path.strip()).name.replace(".JPG", ".tif")
    ids, xyz, sig = [], [], []
    for line in (DBAT / "objpts-pm.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            t = line.split()
            ids.append(t[0])
            xyz.append([float(v) for v in t[1:4]])
            sig.append(max(float(v) for v in t[4:7]) * 1000.0)
    targets = TargetField(np.array(ids), np.array(xyz), np.array(sig), -1)
    index = {t: k for k, t in enumerate(ids)}
    img_idx, tgt, uv = [], [], []
    for line in (DBAT / "markpts.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            i, pid, x, y, _ = (s.strip() for s in line.split(","))
            img_idx.append(int(i) - 1)
            tgt.append(index[pid])
            uv.append((float(x) - 0.5, float(y) - 0.5))
    images = [FieldImage(names[i], None) for i in sorted(names)]
    obs = FieldObservations(np.array(img_idx), np.array(tgt), np.array(uv), sigma_px)
    return FieldData(Sensor(2272, 1704, 3.1911), targets, images, obs, nominal_focal_mm=7.5,
                     default_sigma_px=sigma_px)
