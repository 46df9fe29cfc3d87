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

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

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


def dbat_rows(path):
    """The data lines of one of the data set's text files (no blank or # lines)."""
    return [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def _spread(uv, n):
    """Indices of ``n`` well-spread points of ``uv`` (farthest-point choice, deterministic)."""
    chosen = [int(np.argmax(np.linalg.norm(uv - uv.mean(axis=0), axis=1)))]
    dmin = np.linalg.norm(uv - uv[chosen[0]], axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(dmin)))
        dmin = np.minimum(dmin, np.linalg.norm(uv - uv[chosen[-1]], axis=1))
    return np.array(chosen)


def dbat_marks() -> np.ndarray:
    """PhotoModeler's marks (markpts.txt) as rows ``image id, target id, u, v`` in its own pixel
    convention (subtract 0.5 for fieldcal's)."""
    require("dbat-camcal")
    return np.array([[float(v) for v in ln.split(",")] for ln in dbat_rows(DBAT / "markpts.txt")])


def dbat_image_names() -> dict[int, tuple[str, str]]:
    """Image id -> (the JPEG's file name in the data set, the session's ``images/<name>.tif``)."""
    require("dbat-camcal")
    names = {}
    for line in dbat_rows(DBAT / "images.txt"):
        i, path = line.split(",")
        jpg = path.strip().rsplit("/", 1)[-1]
        names[int(i)] = (jpg, "images/" + jpg.replace(".JPG", ".tif"))
    return names


def write_dbat_photo_session(folder: Path, images: Path | None, *, list_plain: bool, bars: int = 0,
                             pm_survey: bool = False) -> Path:
    """A session of the sheet's photos with marks of the four control points only (``pm_survey``:
    PhotoModeler's 100 adjusted object points as the survey and marks of 5 plain targets per
    photo, tests/field/test_dbat_photos.py's session). The four control points have the
    unit square's corners (ctrlpts-weighted.txt, 0.001 units); ``list_plain`` lists the other 96
    ids without coordinates; ``bars`` (1 or 2) makes it a free network (``field.datum`` "free")
    scaled by that many sides of the square (scale_bars.csv, 1 unit +- 0.0001). ``images``: a
    folder of the TIFFs already written (hard-linked), None: converted from the JPEGs. Returns
    the session's images folder."""
    require("dbat-camcal")
    folder.mkdir(parents=True)
    (folder / "images").mkdir()
    names = {}
    for i, (jpg, name) in dbat_image_names().items():
        names[i] = name
        if images is None:
            gray = cv2.imread(str(DBAT / "images" / jpg), cv2.IMREAD_GRAYSCALE)     # BT.601 luminance
            assert gray is not None and gray.shape == (1704, 2272), jpg
            tifffile.imwrite(folder / name, gray, photometric="minisblack")
        else:
            os.link(images / Path(name).name, folder / name)
    rows = ["id,X,Y,Z,sigma_mm,code"]
    for line in dbat_rows(DBAT / "ctrlpts-weighted.txt"):
        t = [s.strip() for s in line.split(",")]
        rows.append(f"{t[0]},{t[2]},{t[3]},{t[4]},{float(t[5]) * 1000.0:g},")
    rows += [f"{k},,,,," for k in range(2, 98)] if list_plain else []
    if pm_survey:
        pts = (ln.split() for ln in dbat_rows(DBAT / "objpts-pm.txt"))
        rows = ["id,X,Y,Z,sigma_mm,code"] + [f"{t[0]},{t[1]},{t[2]},{t[3]},{max(float(v) for v in t[4:7]) * 1000:.4f},"
                                             for t in pts]
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")
    pm = dbat_marks()
    marks = ["image,target_id,u,v"]
    for i, name in names.items():
        m = pm[(pm[:, 0] == i) & (pm[:, 1] < 1000)]
        for r in (m[_spread(m[:, 2:4], 5)] if pm_survey else pm[(pm[:, 0] == i) & (pm[:, 1] > 1000)]):
            marks.append(f"{name},{int(r[1])},{r[2] - 0.5:.4f},{r[3] - 0.5:.4f}")
    (folder / "marks.csv").write_text("\n".join(marks) + "\n")
    field = {"targets": "targets.csv", "target_polarity": "dark"}
    if bars:
        field["datum"] = "free"
        sides = ["1001,1002,1000.0,0.1", "1003,1001,1000.0,0.1"][:bars]
        (folder / "scale_bars.csv").write_text("from_id,to_id,length_mm,sigma_mm\n" + "\n".join(sides) + "\n")
    manifest = {"schema": "fieldcal.session/1", "method": "field", "camera_id": "olympus-c4040z",
                "session_id": folder.name, "acquired": "2003-08-25",
                "sensor": {"width_px": 2272, "height_px": 1704, "pixel_size_um": 3.1911},
                "lens": {"nominal_focal_mm": 7.5}, "field": field, "images": "images/*.tif",
                "default_sigma_px": 0.1}
    (folder / "session.json").write_text(json.dumps(manifest, indent=2))
    return folder / "images"
