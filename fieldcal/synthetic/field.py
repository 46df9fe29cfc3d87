"""Synthetic field-calibration problems with exact truth.

Two scenarios, both in a world frame with X along the facade (east), Y towards it
(north) and Z up; the cameras stand south of the facade and look north:

``paper_field``
    The geometry of the field paper (METHODS part A): a Phase One iXU150-like camera
    (8208 x 6280 px, 5.3 um, the paper's Table 1 parameters), an 80 m x 30 m facade with
    ~2000 targets of 60 mm on a 1 m grid and up to 1.8 m of depth relief (pilasters
    and balconies), 6 stations (3 on the ground, 3 on a roof) at ~60 m, 12 attitudes
    each (aimed across the facade, rolled by multiples of 90 degrees): 72 images seeing
    100-300 targets each.
``board_field``
    A planar chessboard (13 x 12 corners, 30 mm squares, as J.-Y. Bouguet's example) seen by a
    640 x 480 camera with ~35 px of barrel distortion from ~20 poses at 0.5-0.8 m, flat or
    warped out of its plane (a dome or a fold of tens of microns); the session's targets are
    the board's nominal (flat) coordinates, the images see the warped board.
``wide_field``
    A wide-angle non-metric camera (6000 x 4000 px, 3.9 um, 24 mm, about 20 px of
    barrel distortion in the corners) in front of a 10 m x 4 m wall with up to 1 m of
    relief, 8 stations x 3 rolls = 24 convergent images from 5-7 m.

Every problem carries the truth (camera, poses, exact targets and exact image points)
and what a user would have: surveyed targets with survey noise and measured image
points with image noise. Noise is seeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from fieldcal.model.camera import Camera, Sensor
from fieldcal.session.data import FieldData, FieldImage, FieldObservations, TargetField

__all__ = [
    "IXU150_TABLE1", "WIDE_ANGLE", "BOARD_CAMERA", "SyntheticField", "look_at", "paper_field", "wide_field",
    "faceted_field", "board_field", "board_deflection_mm",
    "add_blunders", "Blunders", "measurements_of", "target_plane_axes", "overlapping_images",
    "MIN_SHARED_TARGETS", "check_point_ids", "with_control_points", "visible_points",
]

IXU150_TABLE1 = {
    "f_mm": 146.39, "xp_mm": 0.27555, "yp_mm": 0.040671,
    "k1": -1.1177e-5, "k2": 1.9235e-9, "k3": -1.5038e-12,
    "p1": -8.1256e-7, "p2": -4.2276e-6, "a1": 1.2759e-6, "a2": 3.8587e-5,
}
"""The paper's Table 1 (the k3 of its initial-value column is a typo; this is the adjusted one)."""

WIDE_ANGLE = {
    "f_mm": 24.0, "xp_mm": 0.05, "yp_mm": -0.03,
    "k1": 3.5e-5, "k2": -3.0e-8, "k3": 1.0e-11,
    "p1": 1.0e-5, "p2": -8.0e-6, "a1": 0.0, "a2": 5.0e-5,
}
"""A non-metric 24 mm camera: about 20 px of barrel distortion in the corners of a 6000 x 4000 sensor."""

BOARD_CAMERA = {
    "f_mm": 4.862, "xp_mm": -0.12, "yp_mm": 0.06,
    "k1": 1.05e-2, "k2": -3.0e-4, "k3": 0.0,
    "p1": 2.0e-5, "p2": -1.5e-5, "a1": 0.0, "a2": 0.0,
}
"""A 640 x 480, 7.4 um camera of f = 657 px (Bouguet's example): ~35 px of barrel distortion in
the corners."""


@dataclass
class SyntheticField:
    """A synthetic field problem: truth plus what a user would measure.

    Attributes
    ----------
    name : str
    camera : Camera
        The true camera.
    targets_true : TargetField
        Exact target coordinates (and plane normals).
    R_world_to_camera : (n_images, 3, 3) ndarray
    center_m : (n_images, 3) ndarray
        True exterior orientations.
    uv_true_px : (m, 2) ndarray
        Exact images of the target centres, aligned with ``data.obs``.
    data : FieldData
        Surveyed (noisy) targets and measured (noisy) image points.
    target_diameter_mm, marker_size_mm : float
        Physical sizes for the renderer.
    """

    name: str
    camera: Camera
    targets_true: TargetField
    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    uv_true_px: np.ndarray
    data: FieldData
    target_diameter_mm: float
    marker_size_mm: float
    settings: dict = field(default_factory=dict)


def target_plane_axes(normals):
    """A target's plane axes: ``e1`` (world X projected into the plane; world Y for a plane
    facing X), ``e2 = n x e1``; returns ``(n, e1, e2)``, each (k, 3). A marker is printed with its
    top towards ``e2`` and its left towards ``-e1``."""
    n = np.asarray(normals, float)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    ref = np.where((np.abs(n[:, 0]) > 0.9)[:, None], [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    e1 = ref - np.sum(ref * n, axis=1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    return n, e1, e2


def look_at(center_m, aim_m, roll_rad=0.0, up=(0.0, 0.0, 1.0)):
    """``R_world_to_camera`` of a camera at ``center_m`` looking at ``aim_m``, rolled about its axis.

    The camera frame is x right, y up, z backwards (docs/conventions.md section 1); with
    ``roll_rad = 0`` the image's y axis is as close to the world ``up`` as possible.
    """
    forward = np.asarray(aim_m, float) - np.asarray(center_m, float)
    z = -forward / np.linalg.norm(forward)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return roll @ R


def visible_points(camera: Camera, Rs, Cs, X, normals, margin_px: float = 15.0, max_incidence_deg: float = 70.0):
    """Which targets each image sees, and their exact image points (vectorised over images).

    Returns ``(image, target, uv_px)`` for the usable pairs: in front of the camera, inside
    the sensor by ``margin_px``, and seen at less than ``max_incidence_deg`` from the normal.
    """
    s = camera.sensor
    Xc = np.einsum("iab,ijb->ija", Rs, X[None, :, :] - Cs[:, None, :])
    view = Cs[:, None, :] - X[None, :, :]
    cos_inc = np.einsum("ijk,jk->ij", view, normals) / np.linalg.norm(view, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -camera.f_mm * Xc[..., :2] / Xc[..., 2:3]
    # cheap pre-selection on the ideal image (distortion is far below 10 % of the half size)
    half = 0.55 * np.array([s.width_px, s.height_px]) * s.pixel_mm
    cand = (Xc[..., 2] < 0) & (np.abs(q) < half).all(axis=-1) & (cos_inc > np.cos(np.radians(max_incidence_deg)))
    img, tgt = np.nonzero(cand)
    uv = s.mm_to_pixel(camera.distort(q[img, tgt], check=False))
    inside = (
        np.isfinite(uv).all(axis=1)
        & (uv[:, 0] >= margin_px) & (uv[:, 0] <= s.width_px - 1 - margin_px)
        & (uv[:, 1] >= margin_px) & (uv[:, 1] <= s.height_px - 1 - margin_px)
    )
    return img[inside], tgt[inside], uv[inside]


def _simulate(name, camera, targets, poses, stations, *, image_noise_px, survey_noise_mm, seed,
              margin_px, target_diameter_mm, marker_size_mm, max_incidence_deg=70.0,
              settings=None, nominal_focal_mm=None) -> SyntheticField:
    rng = np.random.default_rng(seed)
    Rs = np.stack([p[0] for p in poses])
    Cs = np.stack([p[1] for p in poses])
    img, tgt, uv_true = visible_points(camera, Rs, Cs, targets.xyz_m, targets.normals, margin_px,
                                     max_incidence_deg)
    uv_meas = uv_true + rng.normal(0.0, image_noise_px, uv_true.shape)
    surveyed = targets.xyz_m + rng.normal(0.0, survey_noise_mm / 1000.0, targets.xyz_m.shape)
    images = [FieldImage(f"images/{name}_{i + 1:03d}.tif", stations[i]) for i in range(len(poses))]
    data = FieldData(
        sensor=camera.sensor,
        targets=TargetField(targets.ids, surveyed, np.full(len(targets), max(survey_noise_mm, 1e-3)),
                            targets.codes, targets.normals),
        images=images,
        obs=FieldObservations(img, tgt, uv_meas, np.full(len(img), max(image_noise_px, 1e-3))),
        nominal_focal_mm=nominal_focal_mm,
        default_sigma_px=max(image_noise_px, 1e-3),
    )
    return SyntheticField(name, camera, targets, Rs, Cs, uv_true, data, target_diameter_mm,
                          marker_size_mm, dict(settings or {}, image_noise_px=image_noise_px,
                                               survey_noise_mm=survey_noise_mm, seed=seed))


def _grid_targets(xs, zs, depth_fn, keep_fraction, code_rule, rng, prefix):
    xx, zz = np.meshgrid(xs, zs)
    xx, zz = xx.ravel(), zz.ravel()
    ix, iz = np.meshgrid(np.arange(len(xs)), np.arange(len(zs)))
    ix, iz = ix.ravel(), iz.ravel()
    coded = code_rule(ix, iz)
    keep = coded | (rng.random(xx.size) < keep_fraction)
    xx, zz, ix, iz, coded = xx[keep], zz[keep], ix[keep], iz[keep], coded[keep]
    yy = depth_fn(xx, zz)
    xyz = np.stack([xx, yy, zz], axis=1)
    codes = np.full(xx.size, -1, dtype=np.int64)
    codes[coded] = np.arange(coded.sum())
    ids = np.array([f"{prefix}{i + 1:04d}" for i in range(xx.size)])
    normals = np.tile([0.0, -1.0, 0.0], (xx.size, 1))
    return TargetField(ids, xyz, 0.0, codes, normals)


def paper_field(*, seed: int = 0, image_noise_px: float = 0.1, survey_noise_mm: float = 5.0,
                n_attitudes: int = 12, distance_m: float = 60.0, camera: Camera | None = None,
                recess_m: float = 0.0, station_spread_m: float = 25.0) -> SyntheticField:
    """The field paper's geometry (see the module docstring); ~72 images, ~2000 targets.

    Parameters
    ----------
    seed : int
        Seeds the target selection jitter, the noise and the attitude jitter.
    image_noise_px : float
        One-sigma Gaussian noise of u and v [px].
    survey_noise_mm : float
        One-sigma Gaussian noise of each surveyed coordinate [mm]; also the sigma written
        to the targets.
    n_attitudes : int
        Attitudes per station (at most 12).
    """
    rng = np.random.default_rng(seed)
    cam = camera or Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1)

    def relief(x, z):
        pilaster = (np.mod(x + 40.0, 8.0) < 2.0) * 0.6
        balcony = ((np.mod(z, 6.0) > 4.4) & (np.abs(x) < 30.0)) * 1.2
        recess = (np.abs(x) < 14.0) * recess_m
        return -(pilaster + balcony) + recess

    def code_rule(ix, iz):
        return (ix % 6 == 3) & (iz % 5 == 2)

    targets = _grid_targets(np.arange(-39.5, 40.0, 1.0), np.arange(1.0, 30.5, 1.0), relief,
                            0.80, code_rule, rng, "T")
    a = station_spread_m
    stations = [("G1", (-a, -distance_m, 1.5)), ("G2", (0.0, -distance_m, 1.5)),
                ("G3", (a, -distance_m, 1.5)), ("R1", (-a, -distance_m + 2, 30.0)),
                ("R2", (0.0, -distance_m + 2, 30.0)), ("R3", (a, -distance_m + 2, 30.0))]
    poses, names = [], []
    for name, C in stations:
        C = np.asarray(C)
        aims = [(C[0] + dx, 0.0, z) for z in (6.0, 15.0, 24.0) for dx in (-21.0, -7.0, 7.0, 21.0)]
        for a in range(n_attitudes):
            aim = np.array(aims[a])
            aim[0] = np.clip(aim[0], -33.0, 33.0) + rng.normal(0, 1.0)
            roll = np.radians(90.0 * (a % 4) + rng.normal(0, 2.0))
            poses.append((look_at(C, aim, roll), C + rng.normal(0, 0.3, 3)))
            names.append(name)
    return _simulate("paper", cam, targets, poses, names, image_noise_px=image_noise_px,
                     survey_noise_mm=survey_noise_mm, seed=seed + 1, margin_px=20.0,
                     target_diameter_mm=60.0, marker_size_mm=400.0, nominal_focal_mm=150.0,
                     settings={"scenario": "paper", "distance_m": distance_m})


def wide_field(*, seed: int = 0, image_noise_px: float = 0.1, survey_noise_mm: float = 5.0,
               camera: Camera | None = None, keep_fraction: float = 0.92,
               relief: bool = True) -> SyntheticField:
    """A wide-angle non-metric camera in front of a wall with relief (see the module docstring).

    ``keep_fraction`` of the grid's plain targets are kept (at random; 1.0 gives a periodic
    grid), and ``relief=False`` puts every target in the wall's plane."""
    rng = np.random.default_rng(seed)
    cam = camera or Camera.from_dict(Sensor(6000, 4000, 3.9), WIDE_ANGLE)

    def depth(x, z):
        pillar = (np.mod(x + 5.0, 2.5) < 0.8) * 0.5
        shelf = ((z > 1.2) & (z < 2.2) & (np.abs(x) < 3.0)) * 0.5
        return -(pillar + shelf) * float(relief)

    def code_rule(ix, iz):
        return (ix % 4 == 2) & (iz % 3 == 1)

    targets = _grid_targets(np.arange(-4.9, 5.0, 0.35), np.arange(0.2, 4.1, 0.35), depth,
                            keep_fraction, code_rule, rng, "W")
    poses, names = [], []
    station_xy = [(-4.0, -5.5), (-1.5, -6.5), (1.5, -6.5), (4.0, -5.5),
                  (-3.0, -5.0), (0.0, -5.5), (3.0, -5.0), (0.0, -7.0)]
    heights = [0.8, 2.0, 3.2, 1.2, 3.0, 1.0, 2.5, 2.0]
    for s, ((x, y), h) in enumerate(zip(station_xy, heights, strict=True)):
        C = np.array([x, y, h])
        for roll_deg in (0.0, 90.0, 270.0):
            aim = np.array([0.35 * x + rng.normal(0, 0.4), 0.0, 2.0 + rng.normal(0, 0.3)])
            poses.append((look_at(C, aim, np.radians(roll_deg + rng.normal(0, 3.0))), C))
            names.append(f"S{s + 1}")
    return _simulate("wide", cam, targets, poses, names, image_noise_px=image_noise_px,
                     survey_noise_mm=survey_noise_mm, seed=seed + 1, margin_px=15.0,
                     target_diameter_mm=20.0, marker_size_mm=120.0, nominal_focal_mm=24.0,
                     settings={"scenario": "wide"})


def faceted_field(*, seed: int = 0, image_noise_px: float = 0.1, survey_noise_mm: float = 5.0,
                  camera: Camera | None = None, yaws_deg=(30.0, -20.0, 35.0, -30.0, 15.0),
                  columns: int = 6, spacing_m: float = 0.35) -> SyntheticField:
    """The wide-angle camera of :func:`wide_field` in front of a folded wall: vertical panels
    ``columns * spacing_m`` wide, each turned about the vertical by its ``yaws_deg`` (a zig-zag:
    each panel starts where the previous one ends), 4 m high, targets on a ``spacing_m`` grid
    in every panel (the first and last column half a spacing from the folds), plane normals
    of the panels (facing the cameras, south). 8 stations x 3 rolls = 24 convergent images
    from 5-7 m. Targets face several directions: the normals are not one vector."""
    rng = np.random.default_rng(seed)
    cam = camera or Camera.from_dict(Sensor(6000, 4000, 3.9), WIDE_ANGLE)
    width = columns * spacing_m
    yaw = np.radians(np.asarray(yaws_deg, float))
    along = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)     # in-plane, horizontal
    starts = np.vstack([[0.0, 0.0, 0.0], np.cumsum(width * along, axis=0)[:-1]])
    starts -= [0.5 * width * along[:, 0].sum(), 0.0, 0.0]
    a = (np.arange(columns) + 0.5) * spacing_m
    z = np.arange(0.2, 4.05, spacing_m)
    xyz, normals = [], []
    for p in range(len(yaw)):
        aa, zz = np.meshgrid(a, z)
        pts = starts[p] + aa.ravel()[:, None] * along[p] + zz.ravel()[:, None] * [0.0, 0.0, 1.0]
        xyz.append(pts)
        normals.append(np.tile(np.cross(along[p], [0.0, 0.0, 1.0]), (len(pts), 1)))   # towards -Y
    xyz, normals = np.vstack(xyz), np.vstack(normals)
    per = columns * len(z)
    k = np.arange(len(xyz)) % per
    coded = ((k // len(z)) % 3 == 1) & ((k % len(z)) % 3 == 1)
    codes = np.full(len(xyz), -1, np.int64)
    codes[coded] = np.arange(coded.sum())
    ids = np.array([f"F{i + 1:04d}" for i in range(len(xyz))])
    targets = TargetField(ids, xyz, 0.0, codes, normals)
    poses, names = [], []
    station_xy = [(-4.0, -5.5), (-1.5, -6.5), (1.5, -6.5), (4.0, -5.5),
                  (-3.0, -5.0), (0.0, -5.5), (3.0, -5.0), (0.0, -7.0)]
    heights = [0.8, 2.0, 3.2, 1.2, 3.0, 1.0, 2.5, 2.0]
    cy = float(np.mean(xyz[:, 1]))
    for s, ((x, y), h) in enumerate(zip(station_xy, heights, strict=True)):
        C = np.array([x, y + cy, h])
        for roll_deg in (0.0, 90.0, 270.0):
            aim = np.array([0.35 * x + rng.normal(0, 0.4), cy, 2.0 + rng.normal(0, 0.3)])
            poses.append((look_at(C, aim, np.radians(roll_deg + rng.normal(0, 3.0))), C))
            names.append(f"S{s + 1}")
    return _simulate("faceted", cam, targets, poses, names, image_noise_px=image_noise_px,
                     survey_noise_mm=survey_noise_mm, seed=seed + 1, margin_px=15.0,
                     target_diameter_mm=20.0, marker_size_mm=120.0, nominal_focal_mm=24.0,
                     settings={"scenario": "faceted"})


def board_deflection_mm(shape: str, amplitude_mm: float, u, v):
    """The out-of-plane deflection [mm] (towards the cameras) of a warped board at normalised
    board coordinates ``u, v`` in [-1, 1]: ``"flat"`` 0; ``"dome"``
    ``a (1 - (u^2 + v^2) / 2)`` (the middle ``a`` above the corners; in the warp model's terms,
    :mod:`fieldcal.field.board`, ``warp_uu = warp_vv = a / 2``, ``warp_uv = 0``); ``"fold"``
    ``a (1 - |u|)`` (a crease along the middle, ``v`` axis: outside the warp model's terms)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    if shape == "flat":
        return np.zeros(np.broadcast(u, v).shape)
    if shape == "dome":
        return amplitude_mm * (1.0 - 0.5 * (u * u + v * v))
    if shape == "fold":
        return amplitude_mm * (1.0 - np.abs(u)) + 0.0 * v
    raise ValueError(f"shape must be 'flat', 'dome' or 'fold', got {shape!r}")


def board_field(*, seed: int = 0, shape: str = "flat", amplitude_mm: float = 0.05, n_poses: int = 20,
                image_noise_px: float = 0.1, board_sigma_mm: float = 0.01, camera: Camera | None = None,
                corners=(13, 12), square_mm: float = 30.0, print_noise_mm: float = 0.0,
                disc_diameter_mm: float = 12.0) -> SyntheticField:
    """A planar chessboard seen from ``n_poses`` poses (see the module docstring).

    The board lies in the world's ``Z = 0`` plane (normal ``+Z``, towards the cameras), its
    corners on a ``square_mm`` grid centred on the origin. The true corners are displaced
    along ``+Z`` by :func:`board_deflection_mm` (``shape``, ``amplitude_mm``); the session's
    targets are the nominal flat grid with the stated ``board_sigma_mm``; ``print_noise_mm``
    moves every true corner by independent Gaussian errors in all three coordinates (a
    board made worse than stated; drawn after the poses). Poses: the camera
    0.5-0.8 m from the board's middle, tilted 5-40 degrees from its normal in a random
    azimuth, aimed within 40 mm of the middle, rolled by multiples of 90 degrees (+- 10);
    all seeded by ``seed`` (poses, then image noise). For the renderer the corners are discs of
    ``disc_diameter_mm`` (a disc board).
    """
    rng = np.random.default_rng(seed)
    cam = camera or Camera.from_dict(Sensor(640, 480, 7.4), BOARD_CAMERA)
    nx, ny = corners
    gx = (np.arange(nx) - 0.5 * (nx - 1)) * square_mm / 1000.0
    gy = (np.arange(ny) - 0.5 * (ny - 1)) * square_mm / 1000.0
    xx, yy = np.meshgrid(gx, gy)
    nominal = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)
    u, v = nominal[:, 0] / np.abs(gx).max(), nominal[:, 1] / np.abs(gy).max()
    true = nominal.copy()
    true[:, 2] = 1e-3 * board_deflection_mm(shape, amplitude_mm, u, v)
    ids = np.array([f"B{i + 1:03d}" for i in range(len(true))])
    normals = np.tile([0.0, 0.0, 1.0], (len(true), 1))
    targets = TargetField(ids, true, 0.0, np.full(len(true), -1, np.int64), normals)
    poses, names = [], []
    for i in range(n_poses):
        tilt, az = np.radians(rng.uniform(5.0, 40.0)), rng.uniform(0.0, 2 * np.pi)
        dist = rng.uniform(0.5, 0.8)
        C = dist * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        aim = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.04, 0.04), 0.0])
        roll = np.radians(90.0 * (i % 4) + rng.normal(0.0, 10.0))
        poses.append((look_at(C, aim, roll, up=(0.0, 1.0, 0.0)), C))
        names.append(f"P{i + 1:02d}")
    if print_noise_mm > 0:
        true = true + rng.normal(0.0, print_noise_mm / 1000.0, true.shape)
        targets = replace(targets, xyz_m=true)
    sf = _simulate("board", cam, targets, poses, names, image_noise_px=image_noise_px, survey_noise_mm=0.0,
                   seed=seed + 1, margin_px=5.0, target_diameter_mm=disc_diameter_mm, marker_size_mm=20.0,
                   max_incidence_deg=75.0, nominal_focal_mm=cam.f_mm,
                   settings={"scenario": "board", "shape": shape, "amplitude_mm": amplitude_mm})
    sf.data = replace(sf.data, targets=TargetField(ids, nominal, np.full(len(ids), board_sigma_mm),
                                                   targets.codes, normals))
    return sf


MIN_SHARED_TARGETS = 30
"""Targets an image chosen by :func:`overlapping_images` shares with the images chosen before it
(when any image does): well above the identification's six."""


def _roll_class(R_world_to_camera: np.ndarray) -> np.ndarray:
    """Per image, the quarter turn (0-3) of its roll: the image's y axis nearest to world +Z,
    +X, -Z or -X, measured in the image plane."""
    up = np.einsum("iab,b->ia", R_world_to_camera, [0.0, 0.0, 1.0])[:, :2]   # world Z in camera x, y
    ang = np.degrees(np.arctan2(up[:, 0], up[:, 1]))                          # 0 when upright
    return np.round(ang / 90.0).astype(int) % 4


def overlapping_images(sf: SyntheticField, n: int) -> list[int]:
    """``n`` image indices of ``sf`` that calibrate together: each shares targets with the others.

    Greedy, deterministic: the first image is the one sharing the most targets with all the
    others; then, while fewer than ``n`` are chosen, the image that shares at least
    :data:`MIN_SHARED_TARGETS` targets with those chosen (any image, when none does), from a
    station not used yet, at a roll (quarter turn) not used yet, and sharing the most targets,
    in that order of preference. Spreading ``n`` indices evenly over the list instead gives
    images of opposite ends of the field that share nothing: ``fieldcal synth --n-images 4``
    of the paper scenario could not be calibrated (issue 30).

    Returns
    -------
    list of int
        Sorted indices into ``sf.data.images`` (all of them when ``n`` is at least their number).
    """
    n_img = len(sf.data.images)
    if n >= n_img:
        return list(range(n_img))
    obs = sf.data.obs
    seen = np.zeros((n_img, len(sf.data.targets)), bool)
    seen[obs.image, obs.target] = True
    shared_all = seen.astype(np.int64) @ seen.T.astype(np.int64)
    np.fill_diagonal(shared_all, 0)
    stations = np.array([im.station or f"#{i}" for i, im in enumerate(sf.data.images)], object)
    rolls = _roll_class(sf.R_world_to_camera)
    chosen = [int(np.argmax(shared_all.sum(axis=1)))]
    while len(chosen) < n:
        union = seen[chosen].any(axis=0)
        shared = seen[:, union].sum(axis=1)
        key = np.stack([shared >= MIN_SHARED_TARGETS, ~np.isin(stations, stations[chosen]),
                        ~np.isin(rolls, rolls[chosen]), shared], axis=1).astype(np.int64)
        key[chosen] = -1
        order = np.lexsort(key.T[::-1])                 # last key row sorts first: lexsort's rule
        chosen.append(int(order[-1]))
    return sorted(chosen)


def check_point_ids(sf: SyntheticField, n: int, image_indices=None, seed: int = 0) -> list[str]:
    """``n`` target ids to withhold as independent check points (``session.json``
    ``check_points``): spread over the field (:func:`fieldcal.field.check_points.stratified_check_points`)
    among the plain targets seen in two or more of the images ``image_indices`` (default all),
    so that each can be intersected. At most a quarter of those targets.

    Raises
    ------
    InputError
        ``n`` below 1 or above that quarter.
    """
    from fieldcal.errors import InputError
    from fieldcal.field.check_points import stratified_check_points

    obs = sf.data.obs
    keep = np.ones(len(obs.image), bool) if image_indices is None else np.isin(obs.image, list(image_indices))
    pairs = np.unique(np.stack([obs.target[keep], obs.image[keep]], axis=1), axis=0)
    seen = np.bincount(pairs[:, 0], minlength=len(sf.data.targets))
    t = sf.data.targets
    cand = np.flatnonzero((seen >= 2) & (t.codes < 0))
    most = len(cand) // 4
    if not 1 <= int(n) <= most:
        raise InputError(f"--check-points must lie in 1..{most} (a quarter of the {len(cand)} plain targets "
                         f"seen in two or more images), got {n}")
    sub = TargetField(t.ids[cand], t.xyz_m[cand], t.sigma_mm[cand], t.codes[cand],
                      None if t.normals is None else t.normals[cand])
    pick = stratified_check_points(sub, (int(n) - 0.49) / len(cand), seed)
    return sorted(str(x) for x in t.ids[cand][pick])


@dataclass
class Blunders:
    """What :func:`add_blunders` did: indices of corrupted survey rows and observations."""

    survey_targets: np.ndarray
    swapped_observations: np.ndarray


def add_blunders(sf: SyntheticField, *, fraction: float = 0.01, survey_offset_m: float = 0.10,
                 seed: int = 0) -> tuple[SyntheticField, Blunders]:
    """Corrupt a copy of the data with two kinds of blunders.

    ``fraction`` of the targets get their surveyed coordinates moved by
    ``survey_offset_m`` in a random direction, and ``fraction`` of the image observations
    are given wrong identities by swapping the target ids of pairs of observations in the
    same image.
    """
    rng = np.random.default_rng(seed)
    data = sf.data
    xyz = data.targets.xyz_m.copy()
    n_t = max(1, int(round(fraction * len(xyz))))
    bad_t = rng.choice(len(xyz), n_t, replace=False)
    d = rng.normal(size=(n_t, 3))
    xyz[bad_t] += survey_offset_m * d / np.linalg.norm(d, axis=1, keepdims=True)

    target = data.obs.target.copy()
    n_pairs = max(1, int(round(fraction * len(target) / 2)))
    swapped = []
    images = rng.choice(np.unique(data.obs.image), n_pairs)
    for i in images:
        k = np.flatnonzero(data.obs.image == i)
        k = k[~np.isin(k, swapped)]
        if k.size < 2:
            continue
        a, b = rng.choice(k, 2, replace=False)
        target[a], target[b] = target[b], target[a]
        swapped += [a, b]
    obs = replace(data.obs, target=target)
    targets = replace(data.targets, xyz_m=xyz)
    new = replace(sf, data=replace(data, targets=targets, obs=obs))
    return new, Blunders(np.sort(bad_t), np.sort(np.array(swapped, dtype=np.int64)))


def measurements_of(sf: SyntheticField, image_index: int, *, coded: bool = True, max_markers=None,
                    seed: int = 0, extra_blobs: int = 0, corners: bool = False):
    """The detector's output for one image without the pixels: a ``measurements`` table.

    One row per observation of the image in ``sf.data.obs`` (the exact image point plus the
    problem's image noise): a disc, or with ``coded`` an ArUco marker (its code) for a coded
    target. ``max_markers`` keeps that many markers (chosen at random, the others are not
    in the table, as when they are out of view); ``extra_blobs`` adds false discs at random
    positions; ``corners`` gives each marker its four outer corners (``corners_px``: the
    marker's square of ``marker_size_mm``, printed as :func:`target_plane_axes` says, seen by
    the true camera, with the image noise). Rows are shuffled, so their order tells nothing.

    Returns
    -------
    table : pyarrow.Table
        Schema ``measurements``.
    truth : (n,) int ndarray
        The target of every row (-1 for a false disc).
    """
    import pyarrow as pa

    from fieldcal.contract.schemas import arrow_schema

    rng = np.random.default_rng([int(seed), int(image_index)])
    k = np.flatnonzero(sf.data.obs.image == image_index)
    t = sf.data.obs.target[k]
    uv = sf.data.obs.uv_px[k]
    code = np.asarray(sf.targets_true.codes, np.int64)[t] if coded else np.full(len(k), -1)
    marker = code >= 0
    if max_markers is not None and marker.sum() > max_markers:
        drop = rng.choice(np.flatnonzero(marker), int(marker.sum()) - int(max_markers), replace=False)
        keep = np.ones(len(k), bool)
        keep[drop] = False
        uv, code, marker, t = uv[keep], code[keep], marker[keep], t[keep]
    if extra_blobs:
        s = sf.camera.sensor
        fake = rng.uniform([0, 0], [s.width_px - 1, s.height_px - 1], (int(extra_blobs), 2))
        uv = np.concatenate([uv, fake])
        code = np.concatenate([code, np.full(len(fake), -1)])
        marker = np.concatenate([marker, np.zeros(len(fake), bool)])
        t = np.concatenate([t, np.full(len(fake), -1)])
    order = rng.permutation(len(uv))
    uv, code, marker, t = uv[order], code[order], marker[order], t[order]
    n = len(uv)
    schema = arrow_schema("measurements")
    sigma = float(sf.settings.get("image_noise_px", 0.1))
    corner_col = None
    if corners and marker.any():
        corner_col = pa.array([_marker_corners(sf, image_index, int(tt), sigma, rng).tolist() if m else None
                               for m, tt in zip(marker, t, strict=True)], pa.list_(pa.float64()))
    cols = {"image": [""] * n, "blob": np.arange(n, dtype=np.int32), "kind": np.where(marker, "aruco", "disc"),
            "code": pa.array(np.where(marker, code, 0).astype(np.int32), pa.int32(), mask=~marker),
            "u_px": uv[:, 0], "v_px": uv[:, 1], "sigma_px": np.full(n, max(sigma, 1e-3)),
            "diameter_px": np.full(n, 20.0), "contrast": np.full(n, 1000.0), "snr": np.full(n, 100.0),
            "saturated": np.zeros(n, bool), "truncated": np.zeros(n, bool),
            "method": np.where(marker, "aruco", "ellipse"), "corners_px": corner_col}
    arrays = []
    for f in schema:
        v = cols.get(f.name)
        arrays.append(pa.nulls(n, f.type) if v is None else v if isinstance(v, pa.Array) else pa.array(v, f.type))
    return pa.table(arrays, schema=schema), t


def _marker_corners(sf: SyntheticField, i: int, t: int, sigma_px: float, rng) -> np.ndarray:
    """The four outer corners (8,) [px] of target ``t``'s marker in image ``i`` (OpenCV's order:
    top-left, top-right, bottom-right, bottom-left of the printed marker), with noise."""
    tt = sf.targets_true
    normals = tt.normals if tt.normals is not None else np.tile([0.0, -1.0, 0.0], (len(tt), 1))
    _, e1, e2 = target_plane_axes(normals[[t]])
    h = sf.marker_size_mm / 2000.0
    P = tt.xyz_m[t] + h * np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]]) @ np.stack([e1[0], e2[0]])
    uv = sf.camera.project(P, sf.R_world_to_camera[i], sf.center_m[i])
    return (uv + rng.normal(0.0, sigma_px, uv.shape)).reshape(-1)


SHEET_CAMERA = {
    "f_mm": 7.45, "xp_mm": -0.015, "yp_mm": 0.10,
    "k1": 4.5e-3, "k2": -2.0e-5, "p1": 1.0e-5, "p2": -2.0e-5, "a2": -5.0e-4,
}
"""A compact camera like DBAT's Olympus C-4040Z (issue 26): about 60 px of barrel distortion in
the corners of a 1136 x 852 sensor of 6.38 um pixels (half the C-4040Z's rows and columns)."""
SHEET_CONTROL_IDS = ("1001", "1002", "1003", "1004")
"""The control points of :func:`sheet_field`, at the grid's corners (as the DBAT sheet's)."""


def sheet_field(*, seed: int = 0, image_noise_px: float = 0.1, survey_noise_mm: float = 0.0,
                camera: Camera | None = None, n_side: int = 10, spacing_m: float = 0.1) -> SyntheticField:
    """A planar calibration sheet photographed like DBAT's (issue 26 goal 6, a truth analogue).

    ``n_side`` x ``n_side`` plain discs (25 mm) ``spacing_m`` apart in the plane ``Z = 0``
    (normal ``+Z``, towards the cameras), the four corners' ids :data:`SHEET_CONTROL_IDS`
    (``1001`` at ``(0, s)``, ``1002`` at ``(s, s)``, ``1003`` at the origin, ``1004`` at
    ``(s, 0)``, ``s`` the grid's side), the others ``2, 3, ...``. Twenty convergent photos: eight
    azimuths at 40 degrees from the normal (roll 0), the same eight rolled a quarter turn, and four
    near the normal rolled 0, 90, 180 and 270 degrees, all 1.7 m from the sheet's centre."""
    rng = np.random.default_rng(seed)
    cam = camera or Camera.from_dict(Sensor(1136, 852, 6.38), SHEET_CAMERA)
    side = spacing_m * (n_side - 1)
    g = np.arange(n_side) * spacing_m
    xx, yy = (a.ravel() for a in np.meshgrid(g, g))
    corner = {(0.0, side): "1001", (side, side): "1002", (0.0, 0.0): "1003", (side, 0.0): "1004"}
    ids, k = [], 2
    for x, y in zip(xx, yy, strict=True):
        key = (round(float(x), 9), round(float(y), 9))
        name = next((v for (a, b), v in corner.items() if abs(a - key[0]) + abs(b - key[1]) < 1e-9), None)
        if name is None:
            name, k = str(k), k + 1
        ids.append(name)
    xyz = np.stack([xx, yy, np.zeros_like(xx)], axis=1)
    targets = TargetField(np.array(ids), xyz, 0.0, -1, np.tile([0.0, 0.0, 1.0], (len(ids), 1)))
    centre = np.array([side / 2, side / 2, 0.0])
    poses, names = [], []
    for roll_deg, tilt_deg, azimuths in ((0.0, 40.0, range(0, 360, 45)), (90.0, 40.0, range(22, 360, 45)),
                                         (None, 8.0, range(0, 360, 90))):
        for n, az in enumerate(azimuths):
            a, t = np.radians(az + rng.normal(0, 3.0)), np.radians(tilt_deg + rng.normal(0, 2.0))
            C = centre + 1.7 * np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
            aim = centre + np.array([rng.normal(0, 0.03), rng.normal(0, 0.03), 0.0])
            roll = 90.0 * n if roll_deg is None else roll_deg
            poses.append((look_at(C, aim, np.radians(roll + rng.normal(0, 2.0)), up=(0.0, 1.0, 0.0)), C))
            names.append(None)
    return _simulate("sheet", cam, targets, poses, names, image_noise_px=image_noise_px,
                     survey_noise_mm=survey_noise_mm, seed=seed + 1, margin_px=12.0,
                     target_diameter_mm=25.0, marker_size_mm=100.0, nominal_focal_mm=7.5,
                     settings={"scenario": "sheet"})


def with_control_points(sf: SyntheticField, spots_m=((-1.5, 1.0), (1.5, 1.0), (-1.5, 3.0), (1.5, 3.0))):
    """``sf``'s observations with only a few control points surveyed (issue 26): the targets
    nearest each ``(X, Z)`` spot [m] on the wall keep their (noisy) survey, every other target's
    coordinates are unknown (NaN, unsurveyed). Returns ``(data, control)``: the FieldData and
    the control points' target indices."""
    X = sf.data.targets.xyz_m
    control = [int(np.argmin(np.hypot(X[:, 0] - a, X[:, 2] - b))) for a, b in spots_m]
    xyz = np.full_like(X, np.nan)
    xyz[control] = X[control]
    return replace(sf.data, targets=replace(sf.data.targets, xyz_m=xyz)), control
