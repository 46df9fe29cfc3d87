"""Physically exact rendering of synthetic field images (image formation).

What is drawn
-------------
Every target of a :class:`~fieldcal.synthetic.field.SyntheticField` is a flat figure in its
plane (point = the true centre, normal = ``targets_true.normals``): a disc of
``target_diameter_mm`` for a plain target, an ArUco marker of ``marker_size_mm`` (the black
outer square) with a white quiet zone for a coded one. A pixel's value is the mean albedo
over ``supersample x supersample`` regular sub-pixel samples. Pixel ``(u, v)`` covers
``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`` (docs/conventions.md section 1), so its samples sit at
``u - 0.5 + (i + 0.5) / S``, ``i = 0 .. S-1`` (and the same in ``v``).

Each sample is a *measured* image point. It goes the way the contract's model defines:

1. pixel -> image plane [mm] (:meth:`Sensor.pixel_to_mm`),
2. the correction formula (:func:`fieldcal.model.camera.correct`) -> ideal point ``q`` [mm],
3. ray ``d = (qx, qy, -f)`` in the camera frame,
4. cut with the target's plane, expressed in the camera frame:
   ``t = (n . P) / (n . d)``, hit ``t d`` (``P = R (X0 - C)``, ``n = R n_world``),
5. in-plane coordinates ``a = e1 . (t d - P)``, ``b = e2 . (t d - P)`` [m] and the figure test
   (``a^2 + b^2 <= r^2`` for a disc; the marker's cell for a marker).

No ellipse is ever drawn around a projected centre, so the well-known perspective
eccentricity (the centre of the imaged ellipse is not the image of the disc's centre) is in
the pixels exactly as large as it is in nature. Regular 8 x 8 sampling puts the rendered
disc's centroid within 0.005 px (RMS 0.002 px) of the exact area centroid for discs of
14-25 px (aliasing of the regular grid; 16 x 16 gives 0.0016 px).

Occlusion: where figures overlap in an image (the facade's relief brings a nearer target in
front of a farther one), every sample belongs to the nearest figure along its ray; the
truth's ``visible_fraction`` says how much of each figure is left. The relief's own
surfaces are not modelled (nothing but the targets hides anything).

In-plane axes of a target: ``e1`` is the world X axis projected into the plane (the world Y
axis where X is nearly normal to it), ``e2 = n x e1`` ("up" on a facade seen from outside).
An ArUco marker is the canonical image of ``cv2.aruco.generateImageMarker`` (6 x 6 cells
for DICT_4X4_*, incl. the one-cell black border), its row 0 along ``+e2`` and column 0 along
``-e1``, surrounded by a white quiet zone ``quiet_zone_cells`` cells wide.

Adaptive sampling (exact)
-------------------------
The figure is first evaluated at the pixel corners of the target's window. Pixels whose
four corners agree, and which are more than ``_REFINE_RADIUS_PX`` pixels away from any
pixel whose corners disagree, are uniform, and get the value of their corners; the others
get the full ``S x S`` samples. This gives the same numbers as supersampling every pixel
(tested) as long as no feature of the figure is thinner than about two pixels; a target
whose narrowest feature (disc's minor axis, marker cell) is under
``_MIN_ADAPTIVE_FEATURE_PX`` is supersampled everywhere. Saves a factor of 3-10 in work.
The per-target loop only handles windows; each window is vectorised over its samples.

Radiometry
----------
The window of mean albedo is blurred by a Gaussian PSF (``psf_sigma_px``, on the albedo
before the radiometry, so the blur is linear), windows are added into the background, and
the image is made in row strips (bounded memory at 8208 x 6280):
``electrons = exposure * full_well_e * illumination(u, v) * albedo``, with a linear
illumination gradient across the frame, then Poisson shot noise and Gaussian read noise,
``DN = gain * electrons + black_level_dn`` with ``gain = 65535 / full_well_e``, rounded and
clipped to 16 bits (a white surface saturates when ``exposure * illumination * albedo > 1``).

Raster size
-----------
:func:`scaled_field` makes a smaller (or larger) sensor with the same field of view and the
same optics in millimetres, and scales the targets so that they cover about as many pixels
as in the full-size problem (paper scenario: discs ~28 px, wide: ~20 px). Tests render
scale 0.1-0.25; benchmarks render the full-size problems directly.

Sessions on disk (session.json, targets.csv, the images, observations.csv, marks.csv) are
written by :mod:`fieldcal.synthetic.session_writer`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
import pyarrow as pa
from scipy import ndimage

from fieldcal.errors import InputError
from fieldcal.model.camera import Camera, Sensor
from fieldcal.session.data import FieldObservations
from fieldcal.synthetic.field import SyntheticField, target_plane_axes

__all__ = [
    "RenderedImage", "render_image", "scaled_field", "coverage_window", "check_image_index",
    "aruco_cells", "TRUTH_SCHEMA", "FULL_WELL_E", "READ_NOISE_E", "ARUCO_DICTIONARY",
    "NOMINAL_FOCAL_MM",
]

FULL_WELL_E = 20_000.0
"""Default full-well capacity [e-]; 16-bit full scale corresponds to it."""
READ_NOISE_E = 10.0
"""Default read noise [e- rms]."""
ARUCO_DICTIONARY = "DICT_4X4_1000"
NOMINAL_FOCAL_MM = {"paper": 150.0, "wide": 24.0}
"""The lens's nominal focal length written to session.json, per synthetic scenario."""

_REFINE_RADIUS_PX = 2
_MIN_ADAPTIVE_FEATURE_PX = 4.0
_CHUNK_SAMPLES = 1 << 18
_OUTLINE_POINTS = 512
_MAX_WINDOW_PX = 8192
_STRIP_ROWS = 256
_MAX_INCIDENCE_DEG = 85.0

# sample classes and their albedo slots
_BG, _DISC, _INK, _PAPER, _HIDDEN = 0, 1, 2, 3, 4

TRUTH_SCHEMA = pa.schema([
    pa.field("target_index", pa.int64(), nullable=False),
    pa.field("target_id", pa.string(), nullable=False),
    pa.field("kind", pa.string(), nullable=False),
    pa.field("coded", pa.bool_(), nullable=False),
    pa.field("code", pa.int32()),
    pa.field("u_px", pa.float64(), nullable=False),
    pa.field("v_px", pa.float64(), nullable=False),
    pa.field("u_ellipse_px", pa.float64(), nullable=False),
    pa.field("v_ellipse_px", pa.float64(), nullable=False),
    pa.field("u_coverage_px", pa.float64()),
    pa.field("v_coverage_px", pa.float64()),
    pa.field("diameter_px", pa.float64(), nullable=False),
    pa.field("fully_inside", pa.bool_(), nullable=False),
    pa.field("visible_fraction", pa.float64(), nullable=False),
    pa.field("isolated", pa.bool_(), nullable=False),
    pa.field("contrast", pa.float64(), nullable=False),
    pa.field("snr", pa.float64(), nullable=False),
    pa.field("saturated", pa.bool_(), nullable=False),
    pa.field("corners_px", pa.list_(pa.float64())),
], metadata={"doc": (
    "One row per target drawn. u_px, v_px: camera.project of the true centre (exact). "
    "u_ellipse_px, v_ellipse_px: discs: area centroid of the imaged outline (512 rim points "
    "projected exactly with camera.project, polygon centroid: 1e-4 px for a 130 px disc at 70 "
    "deg incidence); markers: intersection of the "
    "diagonals of the projected outer corners. u/v_coverage_px: first moments of the "
    "rendered disc coverage before blur (null for markers). diameter_px: sqrt(4 A / pi) of the "
    "imaged outline (markers: of the black square). fully_inside: the whole outline (disc rim, "
    "marker's black square) lies in the frame. visible_fraction: the part of the figure "
    "(disc; marker with its quiet zone) not hidden by a nearer target (pixels outside the frame "
    "count as visible). isolated: no other visible figure within 4 sigma + 2 px (the blur "
    "margin) of this one's visible figure (markers: incl. the quiet zone). contrast [DN]: "
    "expected |background - figure| at the centre before blur; snr: contrast over the noise "
    "std at the brighter level; saturated: that brighter level reaches 65535 DN. corners_px: markers' 4 outer corners "
    "(u0, v0, ..., u3, v3) in OpenCV's order (top-left, top-right, bottom-right, bottom-left "
    "of the printed marker).")})


@dataclass
class RenderedImage:
    """One rendered image.

    Attributes
    ----------
    pixels : (H, W) uint16 ndarray
        The image [DN].
    truth : pyarrow.Table
        One row per target drawn, schema :data:`TRUTH_SCHEMA`.
    meta : dict
        The radiometric settings used (``gain_dn_per_e``, ``full_well_e``, ``read_noise_e``,
        ``exposure``, ``illumination`` coefficients, albedos, ``black_level_dn``, ...).
    """

    pixels: np.ndarray
    truth: pa.Table
    meta: dict


# --------------------------------------------------------------------------------------
# the markers
# --------------------------------------------------------------------------------------
@functools.cache
def _aruco_dictionary(name: str = ARUCO_DICTIONARY):
    import cv2

    if not hasattr(cv2.aruco, name):
        raise InputError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@functools.cache
def aruco_cells(code: int, dictionary: str = ARUCO_DICTIONARY) -> np.ndarray:
    """The cells of ArUco marker ``code``, black border included: (n, n) bool, True = black.

    Row 0 is the top of the printed marker, column 0 its left (OpenCV's canonical image).
    """
    import cv2

    d = _aruco_dictionary(dictionary)
    n_codes = int(d.bytesList.shape[0])
    if not 0 <= int(code) < n_codes:
        raise InputError(f"ArUco code {code} is outside {dictionary} (0..{n_codes - 1})")
    n = int(d.markerSize) + 2
    img = cv2.aruco.generateImageMarker(d, int(code), n, borderBits=1)
    cells = img < 128
    cells.setflags(write=False)
    return cells


# --------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------
@dataclass
class _Targets:
    """Per-target geometry of one image, in the camera frame [m], and the figure's sizes."""

    index: np.ndarray      # (n,) indices into sf.targets_true
    P: np.ndarray          # (n, 3) centre in the camera frame
    n: np.ndarray          # (n, 3) plane normal in the camera frame
    e1: np.ndarray         # (n, 3) in-plane axes in the camera frame
    e2: np.ndarray
    coded: np.ndarray      # (n,) bool
    code: np.ndarray       # (n,) int (-1 plain)
    radius_m: float        # disc radius
    half_m: float          # half side of a marker's black square
    quiet_m: float         # half side of a marker's quiet zone (outline of the figure)


def _hits(q_mm, f_mm: float, tg: _Targets, j: int):
    """Where the rays of ideal points ``q_mm`` (N, 2) meet the plane of target ``j``.

    Returns plane coordinates ``a, b`` [m] and the ray parameter ``t`` (the hit is ``t d``
    with ``d = (qx, qy, -f)``, so a smaller ``t`` is nearer); NaN where the ray misses the
    plane (behind the camera, parallel)."""
    n, P, e1, e2 = tg.n[j], tg.P[j], tg.e1[j], tg.e2[j]
    qx, qy = q_mm[:, 0], q_mm[:, 1]
    nd = n[0] * qx + n[1] * qy - n[2] * f_mm                      # n . d
    with np.errstate(divide="ignore", invalid="ignore"):
        t = float(n @ P) / nd
    t[~(t > 0)] = np.nan
    # e . (t d - P) = t (e . d) - e . P
    a = t * (e1[0] * qx + e1[1] * qy - e1[2] * f_mm) - float(e1 @ P)
    b = t * (e2[0] * qx + e2[1] * qy - e2[2] * f_mm) - float(e2 @ P)
    return a, b, t


def _in_support(a, b, tg: _Targets, j: int):
    """Is the plane point (a, b) on target ``j``'s figure (disc, or marker with quiet zone)?"""
    with np.errstate(invalid="ignore"):
        if tg.coded[j]:
            return (np.abs(a) <= tg.quiet_m) & (np.abs(b) <= tg.quiet_m)
        return a * a + b * b <= tg.radius_m ** 2


def _classes(camera: Camera, uv_px, tg: _Targets, j: int, occluders=(),
             dictionary=ARUCO_DICTIONARY):
    """Sample class (_BG, _DISC, _INK, _PAPER) of target ``j`` at measured pixels ``uv_px`` (N, 2).

    A sample on the figure of one of the ``occluders`` (target indices) that is nearer to the
    camera along the sample's ray is hidden: class _HIDDEN (its albedo is the occluder's
    business, so it counts as background here)."""
    q = camera.correct(camera.sensor.pixel_to_mm(uv_px))          # ideal points [mm]
    a, b, t = _hits(q, camera.f_mm, tg, j)
    on = _in_support(a, b, tg, j)
    for k in occluders:
        on_k = np.flatnonzero(on)
        if on_k.size == 0:
            break
        ak, bk, tk = _hits(q[on_k], camera.f_mm, tg, k)
        on[on_k[_in_support(ak, bk, tg, k) & (tk < t[on_k])]] = False
    cls = np.full(len(a), _BG, dtype=np.int8)
    if len(occluders):
        cls[_in_support(a, b, tg, j) & ~on] = _HIDDEN
    if not tg.coded[j]:
        cls[on] = _DISC
        return cls
    cls[on] = _PAPER
    with np.errstate(invalid="ignore"):
        inside = np.flatnonzero(on & (np.abs(a) < tg.half_m) & (np.abs(b) < tg.half_m))
    if inside.size:
        cells = aruco_cells(int(tg.code[j]), dictionary)
        ncell = cells.shape[0]
        cell_m = 2 * tg.half_m / ncell
        col = np.clip(np.floor((a[inside] + tg.half_m) / cell_m).astype(int), 0, ncell - 1)
        row = np.clip(np.floor((tg.half_m - b[inside]) / cell_m).astype(int), 0, ncell - 1)
        cls[inside] = np.where(cells[row, col], _INK, _PAPER)
    return cls


def _outline_plane(tg: _Targets, which: str, n_points: int = _OUTLINE_POINTS):
    """Outlines of all targets in their planes: (n, K, 2) plane coordinates (a, b) [m].

    ``which``: "figure" (disc rim, or the quiet zone's square for a marker) or "shape"
    (disc rim, or the black square). Counter-clockwise in (a, b)."""
    th = np.linspace(0.0, 2 * np.pi, n_points, endpoint=False)
    rim = tg.radius_m * np.stack([np.cos(th), np.sin(th)], axis=1)
    h = tg.quiet_m if which == "figure" else tg.half_m
    s = np.linspace(-h, h, n_points // 4, endpoint=False)
    one = np.ones_like(s)
    square = np.concatenate([np.stack([s, -h * one], 1), np.stack([h * one, s], 1),
                             np.stack([-s, h * one], 1), np.stack([-h * one, -s], 1)])
    return np.where(tg.coded[:, None, None], square[None], rim[None])


def _project_plane(camera: Camera, tg: _Targets, ab):
    """Plane coordinates (n, K, 2) [m] of every target -> measured pixels (n, K, 2).

    NaN where a point is not imaged (behind the camera, or ``distort`` does not converge)."""
    Xc = tg.P[:, None, :] + ab[..., :1] * tg.e1[:, None, :] + ab[..., 1:] * tg.e2[:, None, :]
    return camera.project(Xc, np.eye(3), np.zeros(3))


def _polygon_centroid(uv):
    """Areas (n,) and area centroids (n, 2) of closed polygons ``uv`` (n, K, 2)."""
    x, y = uv[..., 0], uv[..., 1]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * y1 - x1 * y
    area = 0.5 * cross.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cx = ((x + x1) * cross).sum(axis=-1) / (6 * area)
        cy = ((y + y1) * cross).sum(axis=-1) / (6 * area)
    return np.abs(area), np.stack([cx, cy], axis=-1)


def _diagonals_crossing(c):
    """Intersections (n, 2) of the diagonals c0-c2 and c1-c3 of quadrilaterals (n, 4, 2)."""
    d1, d2 = c[:, 2] - c[:, 0], c[:, 3] - c[:, 1]
    A = np.stack([d1, -d2], axis=-1)                      # (n, 2, 2): [d1 | -d2]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(A).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.nan_to_num(A))) > 0)
    out = np.full((len(c), 2), np.nan)
    if ok.any():
        st = np.linalg.solve(A[ok], (c[ok, 1] - c[ok, 0])[..., None])[..., 0]
        out[ok] = c[ok, 0] + st[:, :1] * d1[ok]
    return out


def _geometry(camera: Camera, tg: _Targets, margin_px: int):
    """Everything about the targets' images that does not need the pixels (vectorised).

    Returns a dict of arrays over the targets: ``draw`` (imaged as a whole, touching the
    frame), ``window`` (n, 4) (u0, v0, w, h), and, for the targets drawn (NaN otherwise),
    ``center`` (n, 2), ``ellipse`` (n, 2), ``area`` (n,), ``inside`` (n,), ``corners``
    (n, 4, 2) (NaN for discs). The window comes from a coarse outline (128 points; the chord
    error is 3e-4 of the radius, inside the margin), the truth from a fine one
    (:data:`_OUTLINE_POINTS`).
    """
    s = camera.sensor
    n = len(tg.index)
    W, H = s.width_px, s.height_px
    coarse = _project_plane(camera, tg, _outline_plane(tg, "figure", 128))
    ok = np.isfinite(coarse).all(axis=(1, 2))
    with np.errstate(invalid="ignore"):
        lo = np.floor(np.nanmin(coarse, axis=1, initial=np.inf) + 0.5 - margin_px)
        hi = np.ceil(np.nanmax(coarse, axis=1, initial=-np.inf) + 0.5 + margin_px)
    lo = np.where(ok[:, None], lo, 0).astype(np.int64)
    hi = np.where(ok[:, None], hi, 0).astype(np.int64)
    window = np.concatenate([lo, hi - lo], axis=1)
    u0, v0, w, h = window.T
    draw = (ok & (u0 < W) & (v0 < H) & (u0 + w > 0) & (v0 + h > 0)
            & (w <= _MAX_WINDOW_PX) & (h <= _MAX_WINDOW_PX))
    # narrowest feature [px]: the outline's minor width (2 sqrt(2 lambda_min) for points spread
    # evenly over an ellipse; 1.15 x the side of a square), divided into cells for a marker
    d = np.where(ok[:, None, None], coarse, 0.0)
    d = d - d.mean(axis=1, keepdims=True)
    lam_min = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", d, d) / coarse.shape[1])[:, 0]
    cells_across = aruco_cells(0).shape[0] * tg.quiet_m / tg.half_m
    feature = 2.0 * np.sqrt(2.0 * np.maximum(lam_min, 0.0)) / np.where(tg.coded, cells_across, 1.0)
    k = np.flatnonzero(draw)
    sub = _take(tg, k)
    center = np.full((n, 2), np.nan)
    ellipse = np.full((n, 2), np.nan)
    area = np.full(n, np.nan)
    inside = np.zeros(n, bool)
    corners = np.full((n, 4, 2), np.nan)
    if k.size:
        shape = _project_plane(camera, sub, _outline_plane(sub, "shape"))
        draw[k] &= np.isfinite(shape).all(axis=(1, 2))
        center[k] = camera.project(sub.P, np.eye(3), np.zeros(3))
        area[k], ellipse[k] = _polygon_centroid(shape)
        inside[k] = ((shape[..., 0] >= -0.5) & (shape[..., 0] <= W - 0.5)
                     & (shape[..., 1] >= -0.5) & (shape[..., 1] <= H - 0.5)).all(axis=1)
        hm = tg.half_m
        ab = np.array([[-hm, hm], [hm, hm], [hm, -hm], [-hm, -hm]])  # TL, TR, BR, BL of the print
        c = _project_plane(camera, sub, np.broadcast_to(ab, (k.size, 4, 2)))
        c[~sub.coded] = np.nan
        corners[k] = c
        ellipse[k] = np.where(sub.coded[:, None], _diagonals_crossing(c), ellipse[k])
    return {"draw": draw, "window": window, "center": center, "ellipse": ellipse, "area": area,
            "inside": inside, "corners": corners, "feature_px": feature}


def _select_targets(sf: SyntheticField, i: int, targets, coded: bool, marker_size_mm: float,
                    quiet_zone_cells: float) -> _Targets:
    """Targets that image ``i`` can see (in front, facing it, near the frame), camera frame."""
    tt = sf.targets_true
    R, C = sf.R_world_to_camera[i], sf.center_m[i]
    if targets is None:
        idx = np.arange(len(tt))
    else:
        given = targets if isinstance(targets, np.ndarray) else list(targets)
        idx = np.unique(np.asarray(given, dtype=np.int64).reshape(-1))
        if idx.size and (idx.min() < 0 or idx.max() >= len(tt)):
            raise InputError(f"targets: indices must be in 0..{len(tt) - 1}")
    normals = tt.normals if tt.normals is not None else np.tile([0.0, -1.0, 0.0], (len(tt), 1))
    n_w, e1_w, e2_w = target_plane_axes(normals[idx])
    X = tt.xyz_m[idx]
    codes = tt.codes[idx] if coded else np.full(idx.size, -1)
    is_coded = codes >= 0
    radius_m = sf.target_diameter_mm / 2000.0
    half_m = marker_size_mm / 2000.0
    ncell = aruco_cells(0).shape[0]
    quiet_m = half_m * (1.0 + 2.0 * quiet_zone_cells / ncell)
    size_m = np.where(is_coded, quiet_m * np.sqrt(2.0), radius_m)
    P = (X - C) @ R.T
    view = C - X
    dist = np.linalg.norm(view, axis=1)
    cos_inc = np.einsum("ij,ij->i", view, n_w) / dist
    s = sf.camera.sensor
    half_mm = 0.5 * np.array([s.width_px, s.height_px]) * s.pixel_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -sf.camera.f_mm * P[:, :2] / P[:, 2:3]
        reach_mm = sf.camera.f_mm * size_m / np.abs(P[:, 2])
    near = (np.abs(q) < 1.25 * half_mm + reach_mm[:, None]).all(axis=1)
    keep = (P[:, 2] < 0) & (cos_inc > np.cos(np.radians(_MAX_INCIDENCE_DEG))) & near
    return _Targets(idx[keep], P[keep], n_w[keep] @ R.T, e1_w[keep] @ R.T, e2_w[keep] @ R.T,
                    is_coded[keep], codes[keep], radius_m, half_m, quiet_m)


def _take(tg: _Targets, keep) -> _Targets:
    return replace(tg, index=tg.index[keep], P=tg.P[keep], n=tg.n[keep], e1=tg.e1[keep],
                   e2=tg.e2[keep], coded=tg.coded[keep], code=tg.code[keep])


# --------------------------------------------------------------------------------------
# coverage of one window
# --------------------------------------------------------------------------------------
def _sample_offsets(supersample: int):
    """Sub-pixel offsets (S*S, 2) of the regular samples, relative to the pixel centre [px]."""
    o = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = np.meshgrid(o, o)
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def _window_classes_mean(camera, tg, j, u0, v0, h, w, supersample, lut, adaptive, occluders=(),
                         dictionary=ARUCO_DICTIONARY):
    """Mean albedo, visible and hidden figure coverage (h, w) of a window (top-left pixel u0, v0).

    ``lut`` maps the sample classes to albedos; the coverages are the fractions of samples
    on the figure of target ``j`` that are visible / hidden by one of the ``occluders``."""
    if adaptive:
        uc, vc = np.meshgrid(u0 - 0.5 + np.arange(w + 1), v0 - 0.5 + np.arange(h + 1))
        corners = np.stack([uc.ravel(), vc.ravel()], axis=1)
        cc = _classes(camera, corners, tg, j, occluders, dictionary).reshape(h + 1, w + 1)
        same = ((cc[:-1, :-1] == cc[:-1, 1:]) & (cc[:-1, :-1] == cc[1:, :-1])
                & (cc[:-1, :-1] == cc[1:, 1:]))
        size = 2 * _REFINE_RADIUS_PX + 1
        refine = ndimage.binary_dilation(~same, structure=np.ones((size, size), bool))
        albedo = lut[cc[:-1, :-1]].astype(float)
        cover = ((cc[:-1, :-1] != _BG) & (cc[:-1, :-1] != _HIDDEN)).astype(float)
        hidden = (cc[:-1, :-1] == _HIDDEN).astype(float)
    else:
        refine = np.ones((h, w), bool)
        albedo, cover, hidden = np.empty((h, w)), np.empty((h, w)), np.empty((h, w))
    rv, ru = np.nonzero(refine)
    if rv.size:
        offs = _sample_offsets(supersample)
        m = len(offs)
        per = max(1, _CHUNK_SAMPLES // m)
        for s0 in range(0, rv.size, per):
            pv, pu = rv[s0:s0 + per], ru[s0:s0 + per]
            uv = np.stack([((u0 + pu)[:, None] + offs[None, :, 0]).ravel(),
                           ((v0 + pv)[:, None] + offs[None, :, 1]).ravel()], axis=1)
            cls = _classes(camera, uv, tg, j, occluders, dictionary).reshape(-1, m)
            albedo[pv, pu] = lut[cls].mean(axis=1)
            cover[pv, pu] = ((cls != _BG) & (cls != _HIDDEN)).mean(axis=1)
            hidden[pv, pu] = (cls == _HIDDEN).mean(axis=1)
    return albedo, cover, hidden


def coverage_window(sf: SyntheticField, image_index: int, target_index: int, *,
                    supersample: int = 8, adaptive: bool = True, margin_px: int = 2,
                    coded: bool = True, quiet_zone_cells: float = 1.0,
                    marker_size_mm: float | None = None):
    """The unblurred figure of one target in one image, before any radiometry.

    Parameters
    ----------
    sf : SyntheticField
    image_index, target_index : int
        The image and the target (index into ``sf.targets_true``).
    supersample : int
        Samples per pixel along each axis.
    adaptive : bool
        Refine only pixels near an edge (exact for features wider than ~2 px; see the module
        docstring); ``False`` supersamples every pixel.
    margin_px : int
        Pixels added around the figure's outline.

    Returns
    -------
    u0, v0 : int
        Pixel coordinates of the window's top-left pixel (may be outside the frame).
    coverage : (h, w) ndarray
        Disc: the covered fraction of each pixel [0, 1]. Marker: the fraction of each pixel
        that is black ink.
    """
    check_image_index(sf, image_index)
    tg = _select_targets(sf, image_index, [target_index], coded,
                         sf.marker_size_mm if marker_size_mm is None else marker_size_mm,
                         quiet_zone_cells)
    geo = _geometry(sf.camera, tg, margin_px) if len(tg.index) else None
    if geo is None or not geo["draw"][0]:
        raise InputError(f"target {target_index} is not imaged as a whole by image {image_index}")
    u0, v0, w, h = (int(x) for x in geo["window"][0])
    lut = np.array([0.0, 1.0, 1.0, 0.0, 0.0])
    adaptive = adaptive and geo["feature_px"][0] >= _MIN_ADAPTIVE_FEATURE_PX
    cov, _, _ = _window_classes_mean(sf.camera, tg, 0, u0, v0, h, w,
                                     _check_supersample(supersample), lut, adaptive)
    return u0, v0, cov


# --------------------------------------------------------------------------------------
# the image
# --------------------------------------------------------------------------------------
def check_image_index(sf, image_index):
    n = len(sf.R_world_to_camera)
    if not (isinstance(image_index, (int, np.integer)) and 0 <= image_index < n):
        raise InputError(f"image_index must be an integer in 0..{n - 1}, got {image_index!r}")


def _check_supersample(supersample):
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= 64):
        raise InputError(f"supersample must be an integer in 1..64, got {supersample!r}")
    return int(supersample)


def _illumination(meta, u, v):
    """Relative illumination at pixel coordinates (broadcasting) [1 at the frame centre]."""
    g = meta["illumination"]
    return 1.0 + g["gradient"] * (g["cos"] * (u - g["cu"]) / g["width"]
                                  + g["sin"] * (v - g["cv"]) / g["height"])


def render_image(sf: SyntheticField, image_index: int, *, psf_sigma_px: float = 0.8,
                 supersample: int = 8, polarity: str = "dark", exposure: float = 0.6,
                 noise: bool = True, seed: int = 0, targets=None, coded: bool = True,
                 full_well_e: float = FULL_WELL_E, read_noise_e: float = READ_NOISE_E,
                 black_level_dn: float = 0.0, illumination_gradient: float = 0.2,
                 albedo_dark: float = 0.08, albedo_light: float = 0.9,
                 quiet_zone_cells: float = 1.0, adaptive: bool = True) -> RenderedImage:
    """Render image ``image_index`` of a synthetic field, physically (see the module docstring).

    Parameters
    ----------
    sf : SyntheticField
        The problem (true camera, poses, targets); see :func:`scaled_field` for small rasters.
    image_index : int
        Which pose.
    psf_sigma_px : float
        Standard deviation of the Gaussian PSF [px]; 0 for none.
    supersample : int
        Samples per pixel along each axis (``S``; ``S^2`` samples per pixel).
    polarity : {"dark", "bright"}
        Dark discs on a light background, or the reverse. Markers are always black ink on
        white paper.
    exposure : float
        Signal of a white (albedo 1) surface at the frame centre, as a fraction of the full
        well. With the default albedos the background sits at ``0.54`` full scale.
    noise : bool
        Add Poisson shot noise and Gaussian read noise; ``False`` gives the expected image
        (rounded to integers).
    seed : int
        Seeds the noise and the direction of the illumination gradient (with ``image_index``).
    targets : sequence of int, optional
        Draw only these targets (indices into ``sf.targets_true``); default all. Targets the
        image cannot see are left out (no row in ``truth``).
    coded : bool
        Draw coded targets as ArUco markers; ``False`` draws them as plain discs.
    full_well_e, read_noise_e : float
        Sensor: full-well capacity [e-] (mapped to 65535 DN) and read noise [e- rms].
    black_level_dn : float
        Offset added to every pixel [DN].
    illumination_gradient : float
        Relative change of the illumination across the frame along a seeded direction.
    albedo_dark, albedo_light : float
        Reflectances of dark and light surfaces (disc / background / ink / paper).
    quiet_zone_cells : float
        Width of the white margin around each marker [cells].
    adaptive : bool
        Exact adaptive sampling (see the module docstring); ``False`` supersamples every
        pixel of every window (slow; for checking).

    Returns
    -------
    RenderedImage
    """
    check_image_index(sf, image_index)
    supersample = _check_supersample(supersample)
    if polarity not in ("dark", "bright"):
        raise InputError(f"polarity must be 'dark' or 'bright', got {polarity!r}")
    if not (np.isfinite(psf_sigma_px) and psf_sigma_px >= 0):
        raise InputError(f"psf_sigma_px must be >= 0, got {psf_sigma_px}")
    if not (np.isfinite(exposure) and exposure > 0):
        raise InputError(f"exposure must be > 0, got {exposure}")
    if not (0 <= albedo_dark < albedo_light):
        raise InputError(f"albedos must satisfy 0 <= albedo_dark < albedo_light, got "
                         f"{albedo_dark}, {albedo_light}")
    s = sf.camera.sensor
    rng = np.random.default_rng([int(seed), int(image_index)])
    phi = rng.uniform(0.0, 2 * np.pi)
    bg = albedo_light if polarity == "dark" else albedo_dark
    fig = albedo_dark if polarity == "dark" else albedo_light
    lut = np.array([bg, fig, albedo_dark, albedo_light, bg])
    meta = {
        "full_well_e": float(full_well_e), "read_noise_e": float(read_noise_e),
        "gain_dn_per_e": 65535.0 / full_well_e, "black_level_dn": float(black_level_dn),
        "exposure": float(exposure), "polarity": polarity, "psf_sigma_px": float(psf_sigma_px),
        "supersample": supersample, "albedo_background": bg, "albedo_figure": fig,
        "albedo_dark": albedo_dark, "albedo_light": albedo_light, "noise": bool(noise),
        "illumination": {"gradient": float(illumination_gradient), "cos": float(np.cos(phi)),
                         "sin": float(np.sin(phi)), "cu": (s.width_px - 1) / 2.0, "cv": (s.height_px - 1) / 2.0,
                         "width": float(s.width_px), "height": float(s.height_px)},
        "seed": int(seed), "image_index": int(image_index),
    }
    tg = _select_targets(sf, image_index, targets, coded, sf.marker_size_mm, quiet_zone_cells)
    windows, geo, cov_centroid = _draw_windows(sf.camera, tg, psf_sigma_px, supersample, lut, adaptive)
    pixels = _compose(s.width_px, s.height_px, windows, meta, bg, rng, noise)
    truth = _truth_table(sf, tg, geo, cov_centroid, geo["draw"], meta, lut)
    return RenderedImage(pixels, truth, meta)


def _draw_windows(cam: Camera, tg: _Targets, psf_sigma_px, supersample, lut, adaptive):
    """The blurred albedo change of every target's window, with occlusion and isolation.

    Returns the windows ``[(u0, v0, delta (h, w) float32)]``, the geometry of
    :func:`_geometry` with ``visible`` and ``isolated`` added, and the first moments of the
    discs' coverage (n, 2) [px] (NaN for markers)."""
    bg = lut[_BG]
    margin = int(math.ceil(4.0 * psf_sigma_px)) + 2
    geo = _geometry(cam, tg, margin)
    u0s, v0s, ws, hs = geo["window"].T
    draw = geo["draw"]
    n = len(tg.index)
    # figures' bounding boxes (lo_u, lo_v, hi_u, hi_v) [px]: who may hide whom, who is isolated
    box = np.stack([u0s + margin, v0s + margin, u0s + ws - margin, v0s + hs - margin], axis=1)
    box[~draw] = [0, 0, -1, -1]

    def overlapping(grow):
        b = box + np.array([-grow, -grow, grow, grow])
        o = ((b[:, None, 0] < b[None, :, 2]) & (b[None, :, 0] < b[:, None, 2])
             & (b[:, None, 1] < b[None, :, 3]) & (b[None, :, 1] < b[:, None, 3]))
        o[np.arange(n), np.arange(n)] = False
        return o & draw[:, None] & draw[None, :]

    near = overlapping(1)
    windows, masks = [], {}
    cov_centroid = np.full((n, 2), np.nan)
    visible = np.zeros(n)
    # per target window (each one vectorised over its pixels and samples)
    for j in np.flatnonzero(draw):
        u0, v0, w, h = int(u0s[j]), int(v0s[j]), int(ws[j]), int(hs[j])
        exact_adaptive = adaptive and geo["feature_px"][j] >= _MIN_ADAPTIVE_FEATURE_PX
        albedo, cover, hidden = _window_classes_mean(cam, tg, j, u0, v0, h, w, supersample, lut,
                                                     exact_adaptive, np.flatnonzero(near[j]))
        delta = albedo - bg
        covered = cover.sum()
        visible[j] = covered / (covered + hidden.sum()) if covered > 0 else 0.0
        masks[j] = cover > 0
        if not tg.coded[j] and covered > 0:    # first moments of the disc's coverage
            cov_centroid[j] = [(cover.sum(axis=0) @ np.arange(u0, u0 + w)) / covered,
                               (cover.sum(axis=1) @ np.arange(v0, v0 + h)) / covered]
        if psf_sigma_px > 0:
            delta = ndimage.gaussian_filter(delta, psf_sigma_px, mode="constant", cval=0.0,
                                            truncate=4.0)
        windows.append((u0, v0, delta.astype(np.float32)))
    geo["visible"] = visible
    geo["isolated"] = _isolated(masks, u0s, v0s, overlapping(margin), margin, n)
    return windows, geo, cov_centroid


def _isolated(masks, u0s, v0s, candidates, margin, n):
    """Targets whose visible figure has no other figure within ``margin`` pixels (Chebyshev)."""
    isolated = np.ones(n, bool)
    structure = np.ones((2 * margin + 1, 2 * margin + 1), bool)
    for j, k in zip(*np.nonzero(np.triu(candidates)), strict=True):
        mj, mk = masks.get(j), masks.get(k)
        if mj is None or mk is None:
            continue
        # k's mask in j's window, then grown by the margin
        hj, wj = mj.shape
        shifted = np.zeros((hj, wj), bool)
        du, dv = int(u0s[k] - u0s[j]), int(v0s[k] - v0s[j])
        a0, a1 = max(0, dv), min(hj, dv + mk.shape[0])
        b0, b1 = max(0, du), min(wj, du + mk.shape[1])
        if a1 <= a0 or b1 <= b0:
            continue
        shifted[a0:a1, b0:b1] = mk[a0 - dv:a1 - dv, b0 - du:b1 - du]
        if (ndimage.binary_dilation(shifted, structure) & mj).any():
            isolated[j] = isolated[k] = False
    return isolated


def _truth_table(sf, tg, geo, cov_centroid, draw, meta, lut):
    k = np.flatnonzero(draw)
    coded = tg.coded[k]
    u, v = geo["center"][k, 0], geo["center"][k, 1]
    e_white = meta["exposure"] * meta["full_well_e"] * _illumination(meta, u, v)
    e_a = e_white * np.where(coded, lut[_PAPER], lut[_BG])     # marker: paper vs ink
    e_b = e_white * np.where(coded, lut[_INK], lut[_DISC])
    g = meta["gain_dn_per_e"]
    hi = np.maximum(e_a, e_b)
    corners = [c.ravel().tolist() if cd else None
               for c, cd in zip(geo["corners"][k], coded, strict=True)]
    cols = {
        "target_index": tg.index[k], "target_id": sf.targets_true.ids[tg.index[k]],
        "kind": np.where(coded, "aruco", "disc"), "coded": coded,
        "code": pa.array(np.where(coded, tg.code[k], 0), pa.int32(), mask=~coded),
        "u_px": u, "v_px": v,
        "u_ellipse_px": geo["ellipse"][k, 0], "v_ellipse_px": geo["ellipse"][k, 1],
        "u_coverage_px": pa.array(cov_centroid[k, 0], pa.float64(), mask=coded),
        "v_coverage_px": pa.array(cov_centroid[k, 1], pa.float64(), mask=coded),
        "diameter_px": np.sqrt(4.0 * geo["area"][k] / np.pi), "fully_inside": geo["inside"][k],
        "visible_fraction": geo["visible"][k], "isolated": geo["isolated"][k],
        "contrast": g * np.abs(e_a - e_b),
        "snr": np.abs(e_a - e_b) / np.sqrt(hi + meta["read_noise_e"] ** 2),
        "saturated": g * hi + meta["black_level_dn"] >= 65535.0,
        "corners_px": pa.array(corners, pa.list_(pa.float64())),
    }
    arrays = {name: v if isinstance(v, pa.Array) else pa.array(v, TRUTH_SCHEMA.field(name).type)
              for name, v in cols.items()}
    return pa.table([arrays[f.name] for f in TRUTH_SCHEMA], schema=TRUTH_SCHEMA)


def _compose(W, H, windows, meta, bg, rng, noise):
    """Background + blurred windows -> electrons -> noise -> 16-bit, in row strips."""
    out = np.empty((H, W), np.uint16)
    e_white = meta["exposure"] * meta["full_well_e"]
    g, black, read = meta["gain_dn_per_e"], meta["black_level_dn"], meta["read_noise_e"]
    u = np.arange(W, dtype=float)
    v0s = np.array([w[1] for w in windows], int).reshape(-1)
    v1s = np.array([w[1] + w[2].shape[0] for w in windows], int).reshape(-1)
    for r0 in range(0, H, _STRIP_ROWS):
        r1 = min(H, r0 + _STRIP_ROWS)
        albedo = np.full((r1 - r0, W), bg)
        for k in np.flatnonzero((v0s < r1) & (v1s > r0)):
            wu0, wv0, d = windows[k]
            a0, a1 = max(r0, wv0), min(r1, wv0 + d.shape[0])
            b0, b1 = max(0, wu0), min(W, wu0 + d.shape[1])
            if b1 <= b0:
                continue
            albedo[a0 - r0:a1 - r0, b0:b1] += d[a0 - wv0:a1 - wv0, b0 - wu0:b1 - wu0]
        v = np.arange(r0, r1, dtype=float)[:, None]
        electrons = e_white * _illumination(meta, u[None, :], v) * np.maximum(albedo, 0.0)
        if noise:
            electrons = rng.poisson(electrons).astype(float)
            electrons += rng.normal(0.0, read, electrons.shape)
        dn = np.rint(g * electrons + black)
        out[r0:r1] = np.clip(dn, 0, 65535).astype(np.uint16)
    return out


# --------------------------------------------------------------------------------------
# raster size
# --------------------------------------------------------------------------------------
def _max_marker_mm(sf: SyntheticField, radius_m: float, quiet_zone_cells: float) -> float:
    """Largest marker whose quiet zone keeps a disc diameter of clearance from every other disc
    (in the marker's plane; relief can still bring figures together in an image)."""
    tt = sf.targets_true
    ci = np.flatnonzero(tt.codes >= 0)
    if ci.size == 0:
        return np.inf
    normals = tt.normals if tt.normals is not None else np.tile([0.0, -1.0, 0.0], (len(tt), 1))
    _, e1, e2 = target_plane_axes(normals[ci])
    ncell = aruco_cells(0).shape[0]
    factor = 0.5 * (1.0 + 2.0 * quiet_zone_cells / ncell)     # quiet half-side / marker side
    d = tt.xyz_m[None, :, :] - tt.xyz_m[ci][:, None, :]       # (coded, all, 3)
    cheb = np.maximum(np.abs(np.einsum("ijk,ik->ij", d, e1)),
                      np.abs(np.einsum("ijk,ik->ij", d, e2)))
    cheb[np.arange(ci.size), ci] = np.inf
    other_coded = np.zeros(len(tt), bool)
    other_coded[ci] = True
    # plain neighbour: quiet + r + 2 r (gap) <= cheb; coded neighbour: 2 quiet + 2 r <= cheb
    lim_plain = (cheb[:, ~other_coded] - 3 * radius_m) / factor
    lim_coded = (cheb[:, other_coded] - 2 * radius_m) / (2 * factor)
    lim = min(lim_plain.min(initial=np.inf), lim_coded.min(initial=np.inf))
    return float(lim * 1000.0)


def scaled_field(sf: SyntheticField, scale: float, *, target_scale: float | None = None,
                 marker_size_mm: float | None = None, margin_px: float | None = None,
                 quiet_zone_cells: float = 1.0) -> SyntheticField:
    """The same problem on a sensor with ``scale`` times the pixels (same field of view).

    The new sensor has ``round(scale * W) x round(scale * H)`` pixels of
    ``pixel_size_um / scale``; the camera parameters (mm) and the poses are unchanged. The
    discs grow by ``target_scale`` (default ``1 / scale``) so that they keep their size in
    pixels (paper ~28 px, wide ~20 px). Markers grow by the same factor, but no further than
    keeps their quiet zone one disc diameter clear of the neighbouring discs (the grid does
    not grow); pass ``marker_size_mm`` to choose. Note that the perspective eccentricity in
    pixels grows by ``target_scale^2 * scale`` (4 x at scale 0.25).

    The observations are re-projected exactly with the new sensor (``uv_true_px``) and keep
    their noise in pixels; those closer than ``margin_px`` (default: the disc's diameter in
    pixels, at least 10) to the border are dropped.
    """
    if not (np.isfinite(scale) and 0.01 <= scale <= 4.0):
        raise InputError(f"scale must be in 0.01..4, got {scale}")
    s = sf.camera.sensor
    sensor = Sensor(int(round(s.width_px * scale)), int(round(s.height_px * scale)),
                    s.pixel_size_um / scale)
    camera = Camera(sensor, sf.camera.params)
    ts = 1.0 / scale if target_scale is None else float(target_scale)
    diameter_mm = sf.target_diameter_mm * ts
    X = sf.targets_true.xyz_m
    from scipy.spatial import cKDTree

    spacing = cKDTree(X).query(X, k=2)[0][:, 1].min() if len(X) > 1 else np.inf
    if diameter_mm / 1000.0 > 0.8 * spacing:
        raise InputError(f"scaled discs of {diameter_mm:.0f} mm would touch: the targets are "
                         f"{spacing * 1000:.0f} mm apart (lower target_scale)")
    if marker_size_mm is None:
        marker_size_mm = min(sf.marker_size_mm * ts,
                             _max_marker_mm(sf, diameter_mm / 2000.0, quiet_zone_cells))
    obs = sf.data.obs
    uv = camera.project(X[obs.target], sf.R_world_to_camera[obs.image], sf.center_m[obs.image])
    if margin_px is None:
        d_px = sf.camera.f_mm * diameter_mm / 1000.0 / np.median(
            np.linalg.norm(X[obs.target] - sf.center_m[obs.image], axis=1)) / sensor.pixel_mm
        margin_px = max(10.0, float(d_px))
    keep = (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= margin_px)
            & (uv[:, 0] <= sensor.width_px - 1 - margin_px) & (uv[:, 1] >= margin_px)
            & (uv[:, 1] <= sensor.height_px - 1 - margin_px))
    noise_px = obs.uv_px - sf.uv_true_px
    new_obs = FieldObservations(obs.image[keep], obs.target[keep], uv[keep] + noise_px[keep],
                                obs.sigma_px[keep])
    data = replace(sf.data, sensor=sensor, obs=new_obs)
    settings = dict(sf.settings, raster_scale=float(scale), target_scale=ts)
    return replace(sf, camera=camera, uv_true_px=uv[keep], data=data,
                   target_diameter_mm=float(diameter_mm), marker_size_mm=float(marker_size_mm),
                   settings=settings)
