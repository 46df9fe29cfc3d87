"""Synthetic field sessions on disk: the files around the rendered images.

:func:`write_field_session` writes a complete session of docs/conventions.md section 3 (session.json,
targets.csv with the *surveyed* coordinates, images/*.tif rendered by
:func:`fieldcal.synthetic.render.render_image` in a mix of TIFF layouts, and optionally
observations.csv and marks.csv) and returns the truth of every image.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import tifffile

from fieldcal import progress
from fieldcal.errors import InputError
from fieldcal.synthetic.field import SyntheticField
from fieldcal.synthetic.render import ARUCO_DICTIONARY, NOMINAL_FOCAL_MM, check_image_index, render_image

__all__ = ["write_field_session", "TIFF_LAYOUTS"]

TIFF_LAYOUTS = (
    {"tile": (256, 256), "compression": "zstd", "bigtiff": False},
    {"tile": None, "compression": None, "bigtiff": False},
    {"tile": (256, 256), "compression": "adobe_deflate", "bigtiff": True},
    {"tile": None, "compression": None, "bigtiff": True},
)
"""The alternation of TIFF layouts written with ``compression_mix`` (image k uses k mod 4)."""


def _write_tiff(path: Path, pixels: np.ndarray, layout: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    kw = {"photometric": "minisblack", "bigtiff": layout["bigtiff"], "metadata": None}
    if layout["tile"] is not None:
        kw["tile"] = layout["tile"]
    else:
        kw["rowsperstrip"] = 64
    if layout["compression"] is not None:
        kw["compression"] = layout["compression"]
    tifffile.imwrite(path, pixels, **kw)


def _safe_id(name: str) -> str:
    """A session id the schema accepts (``[A-Za-z0-9][A-Za-z0-9._-]*``) made from a folder name."""
    out = re.sub(r"[^A-Za-z0-9._-]", "-", name).lstrip("._-")[:128]
    return out or "session"


def _fmt(x: float, digits: int) -> str:
    return f"{x:.{digits}f}"


def _write_csv(path: Path, header, rows) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


def _spread_choice(uv, n, rng):
    """``n`` indices of well-spread points of ``uv`` (K, 2): greedy farthest-point sampling."""
    if len(uv) <= n:
        return np.arange(len(uv))
    first = int(np.argmax(np.linalg.norm(uv - uv.mean(axis=0), axis=1)))
    chosen = [first]
    dmin = np.linalg.norm(uv - uv[first], axis=1)
    for _ in range(n - 1):
        nxt = int(np.argmax(dmin))
        chosen.append(nxt)
        dmin = np.minimum(dmin, np.linalg.norm(uv - uv[nxt], axis=1))
    return np.array(chosen)


def write_field_session(folder, sf: SyntheticField, *, images: bool = True,
                        observations_csv: bool = False, marks_csv: bool = False, coded: bool = True,
                        psf_sigma_px: float = 0.8, seed: int = 0, compression_mix: bool = True,
                        image_indices=None, polarity: str = "dark", camera_id: str | None = None,
                        session_id: str | None = None, acquired: str = "2026-11-20T09:30:00Z",
                        nominal_focal_mm: float | None = None, marks_error_px: float = 0.5,
                        marks_per_image: tuple[int, int] = (4, 6), marks_images=None,
                        check_points=None, normals: str | None = None, **render_kw) -> dict:
    """Write a complete field session (docs/conventions.md section 3) of a synthetic problem.

    Parameters
    ----------
    folder : path-like
        The session folder (created; existing files of the same names are overwritten).
    sf : SyntheticField
        The problem (e.g. ``scaled_field(paper_field(), 0.25)``).
    images : bool
        Render and write ``images/*.tif``. ``False`` with ``observations_csv=True`` gives an
        observation-only session (session.json, targets.csv, observations.csv).
    observations_csv : bool
        Write ``observations.csv`` from ``sf.data.obs`` (the noisy measurements).
    marks_csv : bool
        Write ``marks.csv``: for every image written (those with markers too), 4-6
        well-spread plain targets (greedy farthest-point choice among the observed plain
        targets at least two diameters from the border), at their exact image position plus
        Gaussian noise of ``marks_error_px`` per axis, as a human would click them.
    marks_images : sequence of int, optional
        The images that get marks (default every image written).
    coded : bool
        Draw coded targets as ArUco markers, write ``field.coded`` and the ``code`` column;
        ``False`` draws them as plain discs and writes no codes.
    psf_sigma_px, seed, polarity, **render_kw
        Passed to :func:`render_image` (``seed`` also seeds the marks).
    compression_mix : bool
        Alternate the TIFF layouts of :data:`TIFF_LAYOUTS` (tiled + zstd, striped
        uncompressed, tiled + deflate BigTIFF, striped uncompressed BigTIFF); ``False``
        writes every image striped and uncompressed.
    image_indices : sequence of int, optional
        The images to include (default all).
    camera_id, session_id, acquired, nominal_focal_mm
        Manifest fields; defaults ``synthetic-<scenario>``, the folder's name, a fixed date,
        and the scenario's nominal focal length (paper 150 mm, wide 24 mm).
    check_points : sequence of str, optional
        Target ids the manifest names as independent check points (``check_points``; e.g.
        :func:`fieldcal.synthetic.field.check_point_ids`).
    normals : {None, "columns", "session"}
        Write the targets' true normals: targets.csv's ``nx,ny,nz`` columns, or the manifest's
        ``field.target_normal`` (every target must face the same way); None writes none.

    Returns
    -------
    dict
        ``folder`` (str), ``session`` (the manifest written), ``images`` (list of image names
        written or listed), ``truth`` ({image name: truth table of :func:`render_image`};
        empty without images), ``layouts`` ({image name: TIFF layout}), ``marks`` (table
        ``image, target_id, u, v, u_true, v_true`` or None).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    n_img = len(sf.data.images)
    idx = np.arange(n_img) if image_indices is None else np.asarray(list(image_indices), np.int64)
    for i in idx:
        check_image_index(sf, int(i))
    if polarity not in ("dark", "bright"):
        raise InputError(f"polarity must be 'dark' or 'bright', got {polarity!r}")
    session = _manifest(folder, sf, idx, coded, polarity, camera_id, session_id, acquired, nominal_focal_mm)
    if check_points:
        session["check_points"] = [str(t) for t in check_points]
    if normals not in (None, "columns", "session"):
        raise InputError(f"normals must be None, 'columns' or 'session', got {normals!r}")
    N = sf.targets_true.normals
    if normals == "session":
        if N is None or not np.allclose(N, N[0], atol=1e-12):
            raise InputError("normals='session' needs every target to face the same way")
        session["field"]["target_normal"] = [float(x) for x in N[0]]
    (folder / "session.json").write_text(json.dumps(session, indent=2) + "\n")
    _write_tables(folder, sf, idx, coded, observations_csv, normals == "columns")
    marks = None
    if marks_csv:
        in_marks = idx if marks_images is None else np.asarray(list(marks_images), np.int64)
        marks = _marks(sf, in_marks, coded, marks_error_px, marks_per_image, seed)
        _write_csv(folder / "marks.csv", ["image", "target_id", "u", "v"],
                   [[r["image"], r["target_id"], _fmt(r["u"], 3), _fmt(r["v"], 3)]
                    for r in marks.to_pylist()])
    truth, layouts = {}, {}
    if images:
        for k, i in enumerate(idx):
            name = sf.data.images[int(i)].file
            r = render_image(sf, int(i), psf_sigma_px=psf_sigma_px, seed=seed, polarity=polarity,
                             coded=coded, **render_kw)
            layout = TIFF_LAYOUTS[k % len(TIFF_LAYOUTS)] if compression_mix else TIFF_LAYOUTS[1]
            _write_tiff(folder / name, r.pixels, layout)
            truth[name] = r.truth
            layouts[name] = dict(layout)
            del r
            progress.emit("images", done=k + 1, total=len(idx), label="rendering images")
    return {"folder": str(folder), "session": session, "images": [sf.data.images[int(i)].file for i in idx],
            "truth": truth, "layouts": layouts, "marks": marks}


def _manifest(folder, sf, idx, coded, polarity, camera_id, session_id, acquired, nominal_focal_mm) -> dict:
    """session.json of the images ``idx`` (docs/conventions.md section 3)."""
    scenario = sf.settings.get("scenario", sf.name)
    if nominal_focal_mm is None:
        nominal_focal_mm = (sf.data.nominal_focal_mm or NOMINAL_FOCAL_MM.get(scenario)
                            or float(round(sf.camera.f_mm)))
    session = {
        "schema": "fieldcal.session/1",
        "method": "field",
        "camera_id": camera_id or f"synthetic-{scenario}",
        "session_id": session_id or _safe_id(folder.resolve().name),
        "acquired": acquired,
        "sensor": sf.camera.sensor.to_dict(),
        "lens": {"nominal_focal_mm": float(nominal_focal_mm)},
        "field": {"targets": "targets.csv", "target_diameter_mm": float(sf.target_diameter_mm),
                  "target_polarity": polarity},
        "images": [{"file": sf.data.images[int(i)].file, "station": sf.data.images[int(i)].station}
                   if sf.data.images[int(i)].station else {"file": sf.data.images[int(i)].file}
                   for i in idx],
        "default_sigma_px": float(sf.data.default_sigma_px),
    }
    if coded:
        session["field"]["coded"] = {"type": "aruco", "dictionary": ARUCO_DICTIONARY,
                                     "marker_size_mm": float(sf.marker_size_mm)}
    return session


def _write_tables(folder, sf, idx, coded, observations_csv, normal_columns=False) -> None:
    """targets.csv (the surveyed coordinates, the true normals with ``normal_columns``) and,
    when asked, observations.csv."""
    t = sf.data.targets
    N = sf.targets_true.normals
    _write_csv(folder / "targets.csv", ["id", "X", "Y", "Z", "sigma_mm", "code"]
               + (["nx", "ny", "nz"] if normal_columns else []),
               [[t.ids[k], _fmt(t.xyz_m[k, 0], 6), _fmt(t.xyz_m[k, 1], 6), _fmt(t.xyz_m[k, 2], 6),
                 _fmt(t.sigma_mm[k], 3), str(int(t.codes[k])) if coded and t.codes[k] >= 0 else ""]
                + ([_fmt(N[k, j], 6) for j in range(3)] if normal_columns else [])
                for k in range(len(t))])
    if observations_csv:
        obs = sf.data.obs
        k = np.flatnonzero(np.isin(obs.image, idx))
        _write_csv(folder / "observations.csv", ["image", "target_id", "u", "v", "sigma_px"],
                   [[sf.data.images[obs.image[m]].file, t.ids[obs.target[m]],
                     _fmt(obs.uv_px[m, 0], 6), _fmt(obs.uv_px[m, 1], 6), _fmt(obs.sigma_px[m], 4)]
                    for m in k])


def _marks(sf, idx, coded, error_px, per_image, seed):
    """Hand marks: 4-6 well-spread plain targets per image at the exact image point + noise."""
    rng = np.random.default_rng([int(seed), 7919])
    s = sf.camera.sensor
    obs = sf.data.obs
    plain = (sf.targets_true.codes < 0) | (not coded)
    d_px = sf.camera.f_mm * sf.target_diameter_mm / 1000.0 / s.pixel_mm
    out = {"image": [], "target_id": [], "u": [], "v": [], "u_true": [], "v_true": []}
    for i in idx:
        k = np.flatnonzero((obs.image == i) & plain[obs.target])
        uv = sf.uv_true_px[k]
        dist = np.linalg.norm(sf.targets_true.xyz_m[obs.target[k]] - sf.center_m[i], axis=1)
        border = np.minimum.reduce([uv[:, 0], uv[:, 1], s.width_px - 1 - uv[:, 0],
                                    s.height_px - 1 - uv[:, 1]]) if len(k) else np.zeros(0)
        k, uv = k[border > 2.0 * d_px / dist], uv[border > 2.0 * d_px / dist]
        n = int(rng.integers(per_image[0], per_image[1] + 1))
        pick = _spread_choice(uv, n, rng)
        noisy = uv[pick] + rng.normal(0.0, error_px, (len(pick), 2))
        out["image"] += [sf.data.images[int(i)].file] * len(pick)
        out["target_id"] += list(sf.targets_true.ids[obs.target[k[pick]]])
        out["u"] += noisy[:, 0].tolist()
        out["v"] += noisy[:, 1].tolist()
        out["u_true"] += uv[pick, 0].tolist()
        out["v_true"] += uv[pick, 1].tolist()
    return pa.table({"image": pa.array(out["image"], pa.string()),
                     "target_id": pa.array(out["target_id"], pa.string()),
                     "u": pa.array(out["u"], pa.float64()), "v": pa.array(out["v"], pa.float64()),
                     "u_true": pa.array(out["u_true"], pa.float64()),
                     "v_true": pa.array(out["v_true"], pa.float64())})
