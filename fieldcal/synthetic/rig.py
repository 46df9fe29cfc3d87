"""Synthetic rig calibrations with exact truth (CONTRACT section 3, "Rig sessions").

Two scenarios, in the world frame of :mod:`fieldcal.synthetic.field` (Z up):

``two_head_rig``
    Two heads with different sensors and lenses on one bar, 0.5 m apart, converging by 10
    degrees, photographing the wide-angle scenario's wall (10 m x 4 m, up to 1 m of relief)
    from its 8 stations at 3 roll angles: 24 exposures, 48 images, the heads' views
    overlapping by most of their frames.
``oblique_rig``
    A five-head oblique system: a nadir head and four heads tilted by 45 degrees (forward,
    back, left, right: little overlap between the obliques), flown over a 100 m x 100 m
    ground field with buildings up to 6 m high, at two heights, on a grid of positions, each
    at four headings (and a few degrees of attitude jitter).

The geometry (the rig, its poses, the targets) depends on nothing but the scenario's
arguments; ``seed`` draws only the noise (image points and survey), so draws of one scenario
with different seeds are Monte Carlo samples of one truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fieldcal.model.camera import Camera, Sensor
from fieldcal.model.rotations import R_from_rotvec
from fieldcal.rig.data import RigData, RigHead
from fieldcal.rig.poses import head_pose
from fieldcal.session.data import FieldData, FieldImage, FieldObservations, TargetField
from fieldcal.synthetic.field import WIDE_ANGLE, look_at, visible_points, wide_field

__all__ = ["SyntheticRig", "two_head_rig", "oblique_rig", "write_rig_session", "head_field",
           "write_rig_image_session"]

SECOND_HEAD = {"f_mm": 20.0, "xp_mm": -0.04, "yp_mm": 0.06, "k1": 6.0e-5, "k2": -8.0e-8, "k3": 3.0e-11,
               "p1": -6.0e-6, "p2": 9.0e-6, "a1": 0.0, "a2": -3.0e-5}
"""The two-head rig's second head: a 20 mm lens on a 5000 x 3500 px, 4.4 um sensor."""
OBLIQUE_LENS = {"f_mm": 30.0, "xp_mm": 0.03, "yp_mm": -0.05, "k1": -2.0e-5, "k2": 1.5e-8, "k3": 0.0,
                "p1": 4.0e-6, "p2": -3.0e-6, "a1": 0.0, "a2": 2.0e-5}
"""The oblique heads' lens (each head its own small variation of it)."""
NADIR_LENS = {"f_mm": 24.0, "xp_mm": 0.05, "yp_mm": -0.03, "k1": 3.5e-5, "k2": -3.0e-8, "k3": 1.0e-11,
              "p1": 1.0e-5, "p2": -8.0e-6, "a1": 0.0, "a2": 5.0e-5}


@dataclass
class SyntheticRig:
    """A synthetic rig problem: truth plus what a user would measure.

    Attributes
    ----------
    cameras : list of Camera
        The true heads.
    R_camera_to_rig : (n_heads, 3, 3) ndarray
    t_camera_in_rig_m : (n_heads, 3) ndarray
        The true relative orientations (the reference: identity and zero).
    R_world_to_rig : (n_exposures, 3, 3) ndarray
    C_rig_m : (n_exposures, 3) ndarray
        The true rig poses.
    targets_true : TargetField
    data : RigData
        Surveyed (noisy) targets and measured (noisy) image points.
    """

    name: str
    cameras: list
    R_camera_to_rig: np.ndarray
    t_camera_in_rig_m: np.ndarray
    R_world_to_rig: np.ndarray
    C_rig_m: np.ndarray
    targets_true: TargetField
    data: RigData
    target_diameter_mm: float
    marker_size_mm: float
    settings: dict = field(default_factory=dict)


def _simulate(name, rig_id, head_names, cameras, R_cr, t, R_wr, C_r, targets, *, image_noise_px,
              survey_noise_mm, seed, margin_px, target_diameter_mm, marker_size_mm, settings) -> SyntheticRig:
    """Images of every head at every exposure, with noise drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    surveyed = targets.xyz_m + rng.normal(0.0, survey_noise_mm / 1000.0, targets.xyz_m.shape)
    tf = TargetField(targets.ids, surveyed, np.full(len(targets), max(survey_noise_mm, 1e-3)), targets.codes,
                     targets.normals)
    n_e = len(R_wr)
    exposures = [f"E{e + 1:03d}" for e in range(n_e)]
    heads, head_data, head_exp = [], [], []
    for h, cam in enumerate(cameras):
        R, C = head_pose(R_wr, C_r, R_cr[h], t[h])
        img, tgt, uv = visible_points(cam, R, C, targets.xyz_m, targets.normals, margin_px)
        uv = uv + rng.normal(0.0, image_noise_px, uv.shape)
        seen = np.unique(img)                       # a head's image of an exposure it saw nothing in is not taken
        local = np.full(n_e, -1, np.int64)
        local[seen] = np.arange(len(seen))
        cid = f"{rig_id}-{head_names[h]}"
        images = [FieldImage(f"images/{exposures[e]}_{head_names[h]}.tif", None) for e in seen]
        obs = FieldObservations(local[img], tgt, uv, np.full(len(img), max(image_noise_px, 1e-3)))
        heads.append(RigHead(cid, cam.sensor, float(round(cam.f_mm))))
        head_data.append(FieldData(sensor=cam.sensor, targets=tf, images=images, obs=obs,
                                   nominal_focal_mm=float(round(cam.f_mm)), default_sigma_px=max(image_noise_px, 1e-3),
                                   meta={"camera_id": cid}))
        head_exp.append(seen)
    data = RigData(rig_id, heads, 0, exposures, head_data, head_exp, meta={"scenario": name})
    return SyntheticRig(name, list(cameras), np.asarray(R_cr, float), np.asarray(t, float), np.asarray(R_wr, float),
                        np.asarray(C_r, float), targets, data, target_diameter_mm, marker_size_mm,
                        dict(settings, image_noise_px=image_noise_px, survey_noise_mm=survey_noise_mm, seed=seed))


def two_head_rig(*, seed: int = 0, image_noise_px: float = 0.1, survey_noise_mm: float = 2.0,
                 convergence_deg: float = 10.0, baseline_m: float = 0.5,
                 head_rotation_arcsec=(0.0, 0.0, 0.0)) -> SyntheticRig:
    """Two convergent, overlapping heads with different sensors and lenses (module docstring).

    The reference head is on the left; the second one ``baseline_m`` to its right (rig +x) and
    turned by ``convergence_deg`` towards it (about the rig's y axis), then by the small rotation
    ``head_rotation_arcsec`` about the rig's axes (a boresight that moved: about x or y)."""
    wf = wide_field(seed=0, survey_noise_mm=0.0)            # the wall and its stations (geometry only)
    targets = wf.targets_true
    cams = [Camera.from_dict(Sensor(6000, 4000, 3.9), WIDE_ANGLE),
            Camera.from_dict(Sensor(5000, 3500, 4.4), SECOND_HEAD)]
    moved = R_from_rotvec(np.radians(np.asarray(head_rotation_arcsec, float) / 3600.0))
    R_cr = np.stack([np.eye(3), moved @ R_from_rotvec([0.0, np.radians(convergence_deg), 0.0])])
    t = np.array([[0.0, 0.0, 0.0], [baseline_m, 0.0, 0.0]])
    geo = np.random.default_rng(12345)
    station_xy = [(-4.0, -5.5), (-1.5, -6.5), (1.5, -6.5), (4.0, -5.5), (-3.0, -5.0), (0.0, -5.5), (3.0, -5.0),
                  (0.0, -7.0)]
    heights = [0.8, 2.0, 3.2, 1.2, 3.0, 1.0, 2.5, 2.0]
    R_wr, C_r = [], []
    for (x, y), z in zip(station_xy, heights, strict=True):
        C = np.array([x, y, z])
        for roll_deg in (0.0, 90.0, 270.0):
            aim = np.array([0.35 * x - 0.25 + geo.normal(0, 0.4), 0.0, 2.0 + geo.normal(0, 0.3)])
            R_wr.append(look_at(C, aim, np.radians(roll_deg + geo.normal(0, 3.0))))
            C_r.append(C)
    return _simulate("two-head", "bar2", ["left", "right"], cams, R_cr, t, np.stack(R_wr), np.stack(C_r), targets,
                     image_noise_px=image_noise_px, survey_noise_mm=survey_noise_mm, seed=seed, margin_px=15.0,
                     target_diameter_mm=20.0, marker_size_mm=120.0,
                     settings={"scenario": "two-head", "convergence_deg": convergence_deg, "baseline_m": baseline_m})


def _ground_field(spacing_m: float = 2.5, half_m: float = 50.0) -> TargetField:
    """Targets on a ground grid with buildings (flat roofs 2-6 m high), all facing up; every
    eighth row and column coded."""
    xs = np.arange(-half_m, half_m + 1e-9, spacing_m)
    xx, yy = np.meshgrid(xs, xs)
    xx, yy = xx.ravel(), yy.ravel()
    ix, iy = np.meshgrid(np.arange(len(xs)), np.arange(len(xs)))
    ix, iy = ix.ravel(), iy.ravel()
    block = (np.mod(xx + half_m, 20.0) < 8.0) & (np.mod(yy + half_m, 20.0) < 8.0)
    zz = np.where(block, 2.0 + np.mod(np.floor((xx + half_m) / 20.0) + 2 * np.floor((yy + half_m) / 20.0), 3) * 2.0,
                  0.0)
    coded = (ix % 8 == 4) & (iy % 8 == 4)
    codes = np.full(len(xx), -1, np.int64)
    codes[coded] = np.arange(coded.sum())
    ids = np.array([f"G{i + 1:05d}" for i in range(len(xx))])
    return TargetField(ids, np.stack([xx, yy, zz], axis=1), 0.0, codes, np.tile([0.0, 0.0, 1.0], (len(xx), 1)))


def oblique_rig(*, seed: int = 0, image_noise_px: float = 0.1, survey_noise_mm: float = 2.0,
                tilt_deg: float = 45.0, heights_m=(20.0, 28.0), grid_m=(-12.0, 12.0)) -> SyntheticRig:
    """The five-head oblique system (module docstring): nadir (the reference), forward, back,
    left and right heads tilted by ``tilt_deg``, 0.15-0.2 m from the nadir head."""
    targets = _ground_field()
    sensor = Sensor(6000, 4000, 3.9)
    cams = [Camera.from_dict(sensor, NADIR_LENS)]
    for k in range(4):
        lens = dict(OBLIQUE_LENS, f_mm=OBLIQUE_LENS["f_mm"] + 0.3 * k, xp_mm=OBLIQUE_LENS["xp_mm"] - 0.02 * k)
        cams.append(Camera.from_dict(sensor, lens))
    a = np.radians(tilt_deg)
    R_cr = np.stack([np.eye(3), R_from_rotvec([a, 0, 0]), R_from_rotvec([-a, 0, 0]), R_from_rotvec([0, a, 0]),
                     R_from_rotvec([0, -a, 0])])
    t = np.array([[0, 0, 0], [0.0, 0.18, -0.02], [0.0, -0.18, -0.03], [-0.15, 0.0, 0.01], [0.16, 0.0, -0.01]])
    geo = np.random.default_rng(54321)
    R_wr, C_r = [], []
    for H in heights_m:
        for x in grid_m:
            for y in grid_m:
                C = np.array([x, y, H]) + geo.normal(0, 0.5, 3)
                for heading in (0.0, 90.0, 180.0, 270.0):
                    R = look_at(C, C - [0.0, 0.0, 1.0], np.radians(heading), up=(0.0, 1.0, 0.0))
                    R_wr.append(R_from_rotvec(geo.normal(0, np.radians(4.0), 3)) @ R)
                    C_r.append(C)
    return _simulate("oblique", "obl5", ["nadir", "fwd", "back", "left", "right"], cams, R_cr, t, np.stack(R_wr),
                     np.stack(C_r), targets, image_noise_px=image_noise_px, survey_noise_mm=survey_noise_mm, seed=seed,
                     margin_px=15.0, target_diameter_mm=200.0, marker_size_mm=600.0,
                     settings={"scenario": "oblique", "tilt_deg": tilt_deg})


def write_rig_session(folder, sr: SyntheticRig, *, session_id: str | None = None,
                      acquired: str = "2026-11-20T09:00:00Z") -> Path:
    """An observation-only rig session on disk (CONTRACT section 3, "Rig sessions"):
    ``session.json`` with the rig, ``targets.csv`` (the surveyed coordinates) and
    ``observations.csv`` (the measured points of every head's images). Returns the folder."""
    import csv
    import json

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    d = sr.data
    cameras = [{"camera_id": hd.camera_id, "sensor": hd.sensor.to_dict(),
                "lens": {"nominal_focal_mm": hd.nominal_focal_mm}} for hd in d.heads]
    images, obs_rows = [], []
    for h, hd in enumerate(d.head_data):
        for i, im in enumerate(hd.images):
            images.append({"file": im.file, "camera": d.heads[h].camera_id,
                           "exposure": d.exposures[d.image_exposure[h][i]]})
        o = hd.obs
        obs_rows += [[hd.images[o.image[k]].file, str(d.targets.ids[o.target[k]]), f"{o.uv_px[k, 0]:.6f}",
                      f"{o.uv_px[k, 1]:.6f}", f"{o.sigma_px[k]:.4f}"] for k in range(len(o))]
    manifest = {"schema": "fieldcal.session/1", "method": "field",
                "session_id": session_id or folder.name, "acquired": acquired,
                "rig": {"rig_id": d.rig_id, "reference": d.heads[d.reference].camera_id, "cameras": cameras},
                "field": {"targets": "targets.csv", "target_diameter_mm": float(sr.target_diameter_mm)},
                "images": images, "default_sigma_px": float(d.head_data[0].default_sigma_px)}
    (folder / "session.json").write_text(json.dumps(manifest, indent=1) + "\n")
    t = d.targets
    with open(folder / "targets.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["id", "X", "Y", "Z", "sigma_mm", "code"])
        w.writerows([[t.ids[k], f"{t.xyz_m[k, 0]:.6f}", f"{t.xyz_m[k, 1]:.6f}", f"{t.xyz_m[k, 2]:.6f}",
                      f"{t.sigma_mm[k]:.3f}", ""] for k in range(len(t))])
    with open(folder / "observations.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["image", "target_id", "u", "v", "sigma_px"])
        w.writerows(obs_rows)
    return folder


def head_field(sr: SyntheticRig, h: int, exposures=None):
    """Head ``h`` of a synthetic rig as a single camera's
    :class:`~fieldcal.synthetic.field.SyntheticField` (the renderer's input): the head's true
    camera and exterior orientations (the rig poses composed with its relative orientation) at
    ``exposures`` (indices; default every exposure), and the exact images of the targets it
    sees. Its images are named ``images/<exposure>_<head>.tif`` as in :func:`write_rig_session`."""
    from fieldcal.synthetic.field import SyntheticField

    e = np.arange(len(sr.R_world_to_rig)) if exposures is None else np.asarray(list(exposures), np.int64)
    cam = sr.cameras[h]
    R, C = head_pose(sr.R_world_to_rig[e], sr.C_rig_m[e], sr.R_camera_to_rig[h], sr.t_camera_in_rig_m[h])
    img, tgt, uv = visible_points(cam, R, C, sr.targets_true.xyz_m, sr.targets_true.normals, 15.0)
    head = sr.data.heads[h].camera_id.rsplit("-", 1)[-1]
    images = [FieldImage(f"images/{sr.data.exposures[k]}_{head}.tif", None) for k in e]
    data = FieldData(sensor=cam.sensor, targets=sr.data.targets, images=images,
                     obs=FieldObservations(img, tgt, uv, np.full(len(img), 0.1)),
                     nominal_focal_mm=sr.data.heads[h].nominal_focal_mm, default_sigma_px=0.1)
    return SyntheticField(f"{sr.name}-{head}", cam, sr.targets_true, R, C, uv, data, sr.target_diameter_mm,
                          sr.marker_size_mm, dict(sr.settings))


def write_rig_image_session(folder, sr: SyntheticRig, *, scale: float = 0.2, exposures=None, plain=(),
                            session_id: str | None = None, acquired: str = "2026-11-20T09:00:00Z",
                            seed: int = 0, psf_sigma_px: float = 0.8) -> dict:
    """A rig session of rendered images (no observations.csv; CONTRACT section 3, "Rig sessions").

    Every head is rendered (:func:`fieldcal.synthetic.render.render_image`) on a sensor of
    ``scale`` times its pixels (the same field of view, :func:`~fieldcal.synthetic.render.scaled_field`:
    the discs grow so that they keep their size in pixels; the markers as far as their quiet
    zones allow, the same for every head), at ``exposures`` (indices; default all). ``plain``:
    ``(head index, exposure index)`` pairs whose image shows its coded targets as plain discs (an
    image with no code to start its identification from). ``targets.csv`` holds the surveyed
    coordinates and the codes (the targets' plane normals, for the eccentricity correction, are
    ``sr.targets_true.normals``). Returns ``{"folder", "images", "scaled"}`` (``scaled``: per head
    the scaled :class:`~fieldcal.synthetic.field.SyntheticField`, its truth).
    """
    import json

    import tifffile

    from fieldcal.synthetic.render import ARUCO_DICTIONARY, render_image, scaled_field

    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    d = sr.data
    e = np.arange(len(sr.R_world_to_rig)) if exposures is None else np.asarray(list(exposures), np.int64)
    fields = [scaled_field(head_field(sr, h, e), scale) for h in range(d.n_heads)]
    marker_mm = min(f.marker_size_mm for f in fields)
    fields = [scaled_field(head_field(sr, h, e), scale, marker_size_mm=marker_mm) for h in range(d.n_heads)]
    plain = {(int(h), int(x)) for h, x in plain}
    images, cameras = [], []
    for h, sf in enumerate(fields):
        cameras.append({"camera_id": d.heads[h].camera_id, "sensor": sf.camera.sensor.to_dict(),
                        "lens": {"nominal_focal_mm": d.heads[h].nominal_focal_mm}})
        for i, k in enumerate(e):
            r = render_image(sf, i, seed=seed, coded=(h, int(k)) not in plain, psf_sigma_px=psf_sigma_px)
            tifffile.imwrite(folder / sf.data.images[i].file, r.pixels)
            images.append({"file": sf.data.images[i].file, "camera": d.heads[h].camera_id,
                           "exposure": d.exposures[k]})
    manifest = {"schema": "fieldcal.session/1", "method": "field", "session_id": session_id or folder.name,
                "acquired": acquired,
                "rig": {"rig_id": d.rig_id, "reference": d.heads[d.reference].camera_id, "cameras": cameras},
                "field": {"targets": "targets.csv", "target_diameter_mm": float(fields[0].target_diameter_mm),
                          "target_polarity": "dark",
                          "coded": {"type": "aruco", "dictionary": ARUCO_DICTIONARY,
                                    "marker_size_mm": round(marker_mm, 6)}},
                "images": images}
    (folder / "session.json").write_text(json.dumps(manifest, indent=1) + "\n")
    t = d.targets
    rows = ["id,X,Y,Z,sigma_mm,code"] + [
        f"{t.ids[k]},{t.xyz_m[k, 0]:.6f},{t.xyz_m[k, 1]:.6f},{t.xyz_m[k, 2]:.6f},{t.sigma_mm[k]:.3f},"
        f"{int(t.codes[k]) if t.codes[k] >= 0 else ''}" for k in range(len(t))]
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")
    return {"folder": str(folder), "images": [im["file"] for im in images], "scaled": fields}
