"""Coded targets: ArUco markers found with OpenCV's ``aruco`` module.

A coded target (docs/conventions.md section 3, ``field.coded``) is an ArUco marker of the session's
dictionary lying in the field's surface; its target point is the marker's centre, the
crossing of the diagonals of its black outer square. Under a central projection lines
stay lines, so the crossing of the imaged diagonals is the image of the centre exactly
(no eccentricity, unlike a disc); lens distortion bends the sides by a negligible amount
over a marker.

Procedure
---------
1. A 16-bit image is stretched to 8 bits (:func:`to_uint8`: percentiles of a strided
   sample, one saturating subtract and one scaled conversion; OpenCV's detector needs 8 bits).
2. Markers are detected on an image reduced ``downscale`` times (``cv2.resize`` with
   ``INTER_AREA`` of the 16-bit pixels, then the stretch), which keeps the marker cells
   several pixels wide and makes the detector's adaptive thresholds many times cheaper on
   a 50-megapixel frame (no full-size 8-bit copy is made).
3. Each corner is refined at full resolution: ``cv2.cornerSubPix`` (the refinement of the
   detector's ``CORNER_REFINE_SUBPIX`` option, which ``downscale=1`` uses inside the
   detector) with a window of about half a marker cell; then, by default, lines are
   fitted to sub-pixel points of the four outer edges and intersected
   (:func:`_refine_by_edges`): cornerSubPix places an L-shaped corner of a blurred square
   ~0.2 px inside it, the edges' lines do not (0.005 px on the tests' markers).
4. The centre is the crossing of the diagonals of the refined corners.

Pixel convention: OpenCV places pixel centres at integer coordinates like fieldcal
(docs/conventions.md section 1); a pixel centre ``x_s`` of an image reduced ``f`` times is at ``f x_s + (f - 1) / 2``
in the full image.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
import pyarrow as pa

from fieldcal.errors import InputError
from fieldcal.measure.imageio import check_image
from fieldcal.measure.measurements import apriori_sigma, empty_measurements, measurements_table
from fieldcal.robust import robust_sigma

__all__ = ["to_uint8", "detect_aruco", "diagonal_crossing", "marker_exclusion_polygons",
           "aruco_dictionary", "DEFAULT_DICTIONARY"]

DEFAULT_DICTIONARY = "DICT_4X4_1000"
_MAX_DETECT_SIDE_PX = 4200
_SIGMA_FLOOR_PX = 0.005
"""Automatic ``downscale``: reduce until the longer side is at most this."""


def to_uint8(image, *, low_percent: float = 0.5, high_percent: float = 99.5,
             n_samples: int = 1 << 16) -> np.ndarray:
    """An 8-bit version of a 16-bit image for OpenCV's detectors, by a percentile stretch.

    ``low_percent`` and ``high_percent`` of a strided sample of about ``n_samples`` pixels
    map to 0 and 255; values outside saturate. Two passes over the image (a saturating
    subtract and a scaled conversion, both OpenCV). An 8-bit image is returned unchanged
    (no copy).
    """
    img = check_image(image)
    if img.dtype == np.uint8:
        return img
    step = max(1, int(math.sqrt(img.size / n_samples)))
    lo, hi = np.percentile(img[::step, ::step], [low_percent, high_percent])
    lo, hi = int(lo), int(max(hi, lo + 1))
    shifted = cv2.subtract(img, (lo, 0, 0, 0))                          # saturates at 0
    return cv2.convertScaleAbs(shifted, alpha=255.0 / (hi - lo))


@functools.cache
def aruco_dictionary(name: str):
    """OpenCV's predefined ArUco dictionary of that name (``"DICT_4X4_1000"``, ...).

    Raises
    ------
    InputError
        Not a name of OpenCV's predefined dictionaries.
    """
    if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
        raise InputError(f"unknown ArUco dictionary {name!r} (an OpenCV name such as "
                         f"'{DEFAULT_DICTIONARY}')")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _detector(dictionary: str, refine_subpix: bool):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = (cv2.aruco.CORNER_REFINE_SUBPIX if refine_subpix
                                     else cv2.aruco.CORNER_REFINE_NONE)
    return cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)


def diagonal_crossing(corners) -> np.ndarray:
    """Crossing of the diagonals c0-c2 and c1-c3 of quadrilaterals (n, 4, 2) -> (n, 2)."""
    c = np.asarray(corners, float).reshape(-1, 4, 2)
    p, r = c[:, 0], c[:, 2] - c[:, 0]
    q, s = c[:, 1], c[:, 3] - c[:, 1]
    cross = r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0]
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / cross
    return p + t[:, None] * r


def _refine_subpix(img, corners, cell_px):
    """``cv2.cornerSubPix`` of every corner (n, 4, 2) in a float32 crop around its marker,
    with a window of about half a cell (the refinement of ``CORNER_REFINE_SUBPIX``)."""
    out = np.array(corners, dtype=np.float64)
    H, W = img.shape
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    for k in range(len(out)):
        hw = int(np.clip(np.rint(0.5 * cell_px[k]), 2, 25))
        lo = np.maximum(np.floor(out[k].min(axis=0)).astype(int) - hw - 3, 0)
        hi = np.minimum(np.ceil(out[k].max(axis=0)).astype(int) + hw + 4, [W, H])
        crop = img[lo[1]:hi[1], lo[0]:hi[0]].astype(np.float32)
        pts = np.ascontiguousarray((out[k] - lo).reshape(-1, 1, 2), dtype=np.float32)
        cv2.cornerSubPix(crop, pts, (hw, hw), (-1, -1), crit)
        out[k] = pts.reshape(4, 2) + lo
    return out


def _bilinear(img, u, v):
    """Bilinear interpolation of ``img`` at float pixel coordinates (any shape), clamped."""
    H, W = img.shape
    u = np.clip(u, 0.0, W - 1.000001)
    v = np.clip(v, 0.0, H - 1.000001)
    x0, y0 = np.floor(u).astype(np.intp), np.floor(v).astype(np.intp)
    fx, fy = u - x0, v - y0
    i00, i01 = img[y0, x0].astype(np.float64), img[y0, x0 + 1].astype(np.float64)
    i10, i11 = img[y0 + 1, x0].astype(np.float64), img[y0 + 1, x0 + 1].astype(np.float64)
    return (i00 * (1 - fx) + i01 * fx) * (1 - fy) + (i10 * (1 - fx) + i11 * fx) * fy


def _refine_by_edges(img, corners, n_cells, *, n_along=40, step_px=0.25):
    """Corners (n, 4, 2) from straight lines fitted to the 4 outer edges of each marker.

    Along each side (15-85 % of its length, away from the rounded corners) the image is
    sampled across the side; the edge point is where the profile crosses the middle of
    the black border's and the quiet zone's levels (medians 0.3-0.45 cells either side).
    A total-least-squares line is fitted to each side's points (one pass without points
    more than 3 MAD off), and adjacent lines are intersected. Unlike a corner detector this
    is not pulled by the blur's rounding of the corner.
    """
    n = len(corners)
    a = corners
    b = np.roll(corners, -1, axis=1)
    d = b - a
    length = np.linalg.norm(d, axis=2, keepdims=True)
    tdir = d / length
    nrm = np.stack([tdir[..., 1], -tdir[..., 0]], axis=-1)
    centre = diagonal_crossing(corners)[:, None, :]
    nrm *= np.sign(np.sum(((a + b) / 2 - centre) * nrm, axis=-1, keepdims=True))   # outwards
    cell = length / n_cells                                               # (n, 4, 1)
    s = np.linspace(0.15, 0.85, n_along)
    base = a[:, :, None, :] + s[None, None, :, None] * d[:, :, None, :]   # (n, 4, m, 2)

    def at(offset):                                     # samples offset along the normal
        p = base + offset[..., None] * nrm[:, :, None, :]
        return _bilinear(img, p[..., 0], p[..., 1])

    lv = [at(np.broadcast_to(f * cell, (n, 4, n_along))) for f in (-0.45, -0.3, 0.3, 0.45)]
    lo = np.median(np.concatenate(lv[:2], axis=2), axis=2)[..., None, None]
    hi = np.median(np.concatenate(lv[2:], axis=2), axis=2)[..., None, None]
    reach = np.minimum(0.4 * cell, 6.0)                                   # (n, 4, 1)
    k = int(np.ceil(reach.max() / step_px))
    off = np.arange(-k, k + 1) * step_px                                 # (K,)
    p = base[:, :, :, None, :] + off[None, None, None, :, None] * nrm[:, :, None, None, :]
    prof = _bilinear(img, p[..., 0], p[..., 1])                          # (n, 4, m, K)
    z = (prof - lo) / np.where(hi != lo, hi - lo, 1.0)
    inside_reach = np.abs(off)[None, None, None, :] <= reach[..., None]
    above = (z > 0.5) & inside_reach
    j = np.clip(np.argmax(above, axis=-1), 1, off.size - 1)              # first white sample
    z0 = np.take_along_axis(z, (j - 1)[..., None], -1)[..., 0]
    z1 = np.take_along_axis(z, j[..., None], -1)[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.clip((0.5 - z0) / (z1 - z0), 0.0, 1.0)
    e_off = off[j - 1] + step_px * np.nan_to_num(frac, nan=0.5)
    ok = above.any(axis=-1) & (z0 <= 0.5)
    pts = base + e_off[..., None] * nrm[:, :, None, :]                    # (n, 4, m, 2)

    w = ok.astype(float)
    for _ in range(2):                                  # TLS line, then without outliers
        cnt = np.maximum(w.sum(axis=2, keepdims=True), 1.0)
        c = (pts * w[..., None]).sum(axis=2, keepdims=True) / cnt[..., None]
        X = (pts - c) * np.sqrt(w)[..., None]
        cov = np.einsum("nkmi,nkmj->nkij", X, X)
        _, vec = np.linalg.eigh(cov)
        direction = vec[..., :, 1]                                         # (n, 4, 2)
        normal = np.stack([-direction[..., 1], direction[..., 0]], axis=-1)
        r = np.einsum("nkmi,nki->nkm", pts - c, normal)
        sig = robust_sigma(np.where(ok, r, np.nan), axis=2, keepdims=True)
        w = (ok & (np.abs(r) <= np.maximum(3 * np.nan_to_num(sig), 0.05))).astype(float)
    p0 = c[:, :, 0, :]
    q0, dq = np.roll(p0, 1, axis=1), np.roll(direction, 1, axis=1)      # side k-1 meets side k
    A = np.stack([direction, -dq], axis=-1)
    good = np.abs(np.linalg.det(A)) > 1e-6
    A[~good] = np.eye(2)
    t = np.linalg.solve(A, (q0 - p0)[..., None])[..., 0]
    refined = p0 + t[..., :1] * direction
    enough = (w.sum(axis=2) >= max(6, n_along // 5)).all(axis=1) & good.all(axis=1)
    moved = np.linalg.norm(refined - corners, axis=2).max(axis=1) < cell[:, 0, 0]
    keep = enough & moved & np.isfinite(refined).all(axis=(1, 2))
    # precision: each line's offset is known to rms / sqrt(points); a centre from the four
    # lines about as well (two lines per axis, each corner from two of them)
    used = np.maximum(w.sum(axis=2), 1.0)
    line_sigma = np.sqrt((w * r**2).sum(axis=2) / used) / np.sqrt(used)        # (n, 4)
    sigma = np.where(keep, np.sqrt(np.mean(line_sigma**2, axis=1)), np.nan)
    return np.where(keep[:, None, None], refined, corners), sigma


def _side_samples(img, corners, offset_cells, n_cells, n_per_side=24):
    """Pixel values along the 4 sides, moved ``offset_cells`` cells outwards (n, 4*n_per_side)."""
    c = corners
    centre = diagonal_crossing(c)[:, None, :]
    t = (np.arange(n_per_side) + 0.5) / n_per_side
    a, b = c, np.roll(c, -1, axis=1)
    pts = a[:, :, None, :] + t[None, None, :, None] * (b - a)[:, :, None, :]   # (n, 4, k, 2)
    # a marker of n cells: moving a point k cells outwards scales it about the centre
    scale = 1.0 + offset_cells * 2.0 / n_cells
    pts = centre[:, :, None, :] + scale * (pts - centre[:, :, None, :])
    u = np.clip(np.rint(pts[..., 0]).astype(int), 0, img.shape[1] - 1)
    v = np.clip(np.rint(pts[..., 1]).astype(int), 0, img.shape[0] - 1)
    return img[v, u].reshape(len(c), -1).astype(float)


def detect_aruco(image, dictionary: str = DEFAULT_DICTIONARY, *, downscale: int | None = None,
                 refine: str = "edges", image_name: str = "") -> pa.Table:
    """Detect ArUco markers and measure their centres.

    Parameters
    ----------
    image : (H, W) uint8 or uint16 ndarray
        The pixels [DN].
    dictionary : str
        OpenCV's name of the dictionary (docs/conventions.md: the session's ``field.coded.dictionary``).
    downscale : int, optional
        Detect on an image reduced this many times, then refine the corners at full
        resolution; default: the smallest factor that brings the longer side to at most
        4200 px (1 for small images, 2 for 8208 x 6280 and 6000 x 4000). Marker cells
        should stay ~10 px or more wide in the reduced image: at 4x the paper's 184 px
        markers (7.7 px cells) are still found, but markers with large white interiors
        start to be missed (tests).
    refine : {"edges", "subpix"}
        Final corner refinement: ``"subpix"`` stops after ``cornerSubPix`` (OpenCV's
        ``CORNER_REFINE_SUBPIX``); ``"edges"`` (default, measured more accurate: see
        ``bench/README_extract.md``) then intersects lines fitted to the outer edges.
    image_name : str
        Written to the ``image`` column.

    Returns
    -------
    pyarrow.Table
        Schema ``measurements``, ``kind="aruco"``, ``code`` the marker id, ``u_px, v_px``
        the crossing of the diagonals, ``corners_px`` the 4 refined corners (OpenCV's order),
        ``diameter_px`` the mean side, ``contrast`` and ``snr`` from the black border and the
        quiet zone around it.
    """
    img = check_image(image)
    if downscale is None:
        downscale = max(1, math.ceil(max(img.shape) / _MAX_DETECT_SIDE_PX))
    if not (isinstance(downscale, (int, np.integer)) and 1 <= downscale <= 32):
        raise InputError(f"downscale must be an integer in 1..32, got {downscale!r}")
    if refine not in ("edges", "subpix"):
        raise InputError(f"refine must be 'edges' or 'subpix', got {refine!r}")
    if downscale == 1:
        corners, ids, _ = _detector(dictionary, True).detectMarkers(to_uint8(img))
    else:
        # reduce the 16-bit pixels (a view cropped to whole blocks, so that the reduction is
        # exactly `downscale`), then stretch the small image to 8 bits
        Hc, Wc = (img.shape[0] // downscale) * downscale, (img.shape[1] // downscale) * downscale
        small = cv2.resize(img[:Hc, :Wc], (Wc // downscale, Hc // downscale),
                           interpolation=cv2.INTER_AREA)
        corners, ids, _ = _detector(dictionary, False).detectMarkers(to_uint8(small))
    if ids is None or len(ids) == 0:
        return empty_measurements()
    ids = np.asarray(ids).reshape(-1)
    c = np.concatenate([np.asarray(k, float).reshape(1, 4, 2) for k in corners])
    side = np.linalg.norm(c - np.roll(c, -1, axis=1), axis=2).mean(axis=1)
    n_cells = aruco_dictionary(dictionary).markerSize + 2
    if downscale > 1:
        c = downscale * c + (downscale - 1) / 2.0
        side = side * downscale
        c = _refine_subpix(img, c, side / n_cells)
    edge_sigma = np.full(len(c), np.nan)
    if refine == "edges":
        # twice: a corner that the detector misplaced (e.g. where something dark touches the
        # marker) skews two sides; the second pass samples along the corrected ones
        c, _ = _refine_by_edges(img, c, n_cells)
        c, edge_sigma = _refine_by_edges(img, c, n_cells)
    # one row per marker id: a duplicate id (never expected) keeps the larger marker
    order = np.argsort(-side)
    _, first = np.unique(ids[order], return_index=True)
    keep = np.sort(order[first])
    ids, c, edge_sigma = ids[keep], c[keep], edge_sigma[keep]
    side = np.linalg.norm(c - np.roll(c, -1, axis=1), axis=2).mean(axis=1)
    centre = diagonal_crossing(c)
    diag = np.stack([np.linalg.norm(c[:, 2] - c[:, 0], axis=1),
                     np.linalg.norm(c[:, 3] - c[:, 1], axis=1)], axis=1)

    contrast, snr, saturated, truncated = _marker_quality(img, c, n_cells)
    # a-priori sigma: from the edge lines' scatter (refine="edges", with a floor for the
    # model), else the cornerSubPix bias dominates (~0.02 px at the centre, tests)
    sigma = np.where(np.isfinite(edge_sigma), np.hypot(edge_sigma, _SIGMA_FLOOR_PX),
                     np.hypot(apriori_sigma(snr, 4.0 * side / math.pi), 0.02))
    cols = {
        "kind": ["aruco"] * len(ids), "code": pa.array(ids.astype(np.int32)),
        "u_px": centre[:, 0], "v_px": centre[:, 1],
        "sigma_px": sigma,
        "diameter_px": side, "major_px": diag.max(axis=1) / math.sqrt(2.0),
        "minor_px": diag.min(axis=1) / math.sqrt(2.0),
        "roundness": diag.min(axis=1) / diag.max(axis=1),
        "contrast": contrast, "snr": snr, "saturated": saturated, "truncated": truncated,
        "method": ["aruco"] * len(ids),
        "corners_px": pa.array(c.reshape(len(ids), 8).tolist(), pa.list_(pa.float64())),
    }
    return measurements_table(cols, image_name)


def _marker_quality(img, c, n_cells):
    """Contrast [DN] and SNR from the black border and the quiet zone around it, and the
    saturated / truncated flags, of markers with corners ``c`` (n, 4, 2) [px]; each (n,)."""
    inner = _side_samples(img, c, -0.5, n_cells)     # middle of the black border
    outer = _side_samples(img, c, +0.5, n_cells)     # middle of the white quiet zone
    contrast = np.abs(np.median(outer, axis=1) - np.median(inner, axis=1))
    noise = np.maximum(robust_sigma(outer - np.median(outer, axis=1, keepdims=True), axis=1), 0.3)
    snr = contrast / noise
    H, W = img.shape
    truncated = ((c[..., 0] < 1) | (c[..., 1] < 1) | (c[..., 0] > W - 2) | (c[..., 1] > H - 2)).any(1)
    sat = np.iinfo(img.dtype).max
    lo = np.clip(np.floor(c.min(axis=1)).astype(int), 0, [W - 1, H - 1])
    hi = np.clip(np.ceil(c.max(axis=1)).astype(int) + 1, 1, [W, H])
    saturated = np.array([bool((img[lo[k, 1]:hi[k, 1], lo[k, 0]:hi[k, 0]] >= sat).any())
                          for k in range(len(c))], dtype=bool)
    return contrast, snr, saturated, truncated


def marker_exclusion_polygons(table: pa.Table, *, grow: float = 1.5) -> list[np.ndarray]:
    """Outlines (4, 2) [px] of the markers in ``table``, scaled by ``grow`` about the centre.

    The default covers the black square, its one-cell quiet zone and a margin, so that the
    disc detector skips the marker's black cells.
    """
    if table.num_rows == 0:
        return []
    kind = np.asarray(table.column("kind").to_pylist())
    rows = np.flatnonzero(kind == "aruco")
    corners = table.column("corners_px").to_pylist()
    out = []
    for k in rows:
        c = np.asarray(corners[k], float).reshape(4, 2)
        m = diagonal_crossing(c[None])[0]
        out.append(m + grow * (c - m))
    return out
