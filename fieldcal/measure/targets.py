"""Circular targets in an image: detection, sub-pixel centres and quality figures.

The field method (METHODS part A) needs the image of every circular target to a few
hundredths of a pixel. This module finds dark (or bright) discs in a 8- or 16-bit image
and measures each one in a small window, coarse to fine, so that no stage touches the
whole frame more than once (a strided sample of it) and no full-image float copy or
full-image labelling is made (figures for a 8208 x 6280 frame: bench/README_extract.md):

1. **Candidates** (whole image, cheap). The image is sampled every ``step`` pixels in both
   directions (a strided view, no averaging: ``step`` is chosen so that every disc of at
   least ``min_diameter_px`` has a sample in its flat interior). On that small image a
   morphological black (white) top-hat, with a square wider than the largest disc,
   removes the background; samples more than a few noise sigmas above it are grouped
   into connected components, one per candidate; top-hat-weighted moments give a first
   position and size.
2. **Windows** (per candidate). A square window around each candidate, sized from its
   coarse extent, is cut out; same-size windows are stacked and measured together
   (vectorised over windows, no loop per target or per pixel). A window found too small
   for its blob (the blob reaches the window's edge or comes within 3 px of its ring) is
   measured once more, larger.
3. **Measurement** (per window, the paper's procedure, METHODS part B section 1.2.1, with
   the polarity handled and the local background removed):

   - background: a plane fitted to the window's outer 1-pixel ring, without the ring
     pixels more than 4 noise sigmas from its median (a neighbour or clutter reaching into
     the ring); the noise sigma from differences of neighbouring ring pixels. For a dark
     figure on a lit surface the signal ``c0 (bg - raw) / bg`` is used: the figure's
     contrast scales with the illumination like the background does, so this removes
     the shading's tilt across the window;
   - the figure's level ``C`` (contrast) from the 3 x 3 mean around the extreme pixel
     near the candidate;
   - the threshold: ``"centroid"`` uses the paper's iterative method (isodata: start at
     the window mean, split, take the mean of the two class means, repeat), kept within
     ``[0.3, 0.7] C`` so that a stronger neighbour cannot capture it; ``"ellipse"`` uses
     ``C / 2``, where a blurred edge is steepest and where a symmetric blur leaves it;
   - region growing: the 8-connected component of pixels beyond the threshold that holds
     the extreme pixel (all windows labelled in one call, stacked in a column);
   - the centre, by one of two methods:

     ``"ellipse"``: sub-pixel edge points where the threshold level crosses the pixel
     grid (linear interpolation between the outermost region pixel of every row and
     column and its outside neighbour), and a conic fitted to them (algebraic fit with
     the Euclidean-invariant constraint ``a + c = 1``); the centre of the conic. Its
     precision reaches the Cramer-Rao bound of a disc in white noise (tests); the edge
     points' RMS distance to the conic is the shape figure that rejects squares.

     ``"centroid"``: the grey centroid with squared weights of the background-removed
     signal, over the region grown by ``2`` pixels, after bilinear interpolation onto a
     grid ``upsample`` times finer. The interpolation is done in closed form: the sum over
     the fine grid of ``F^2 (1, x, y)`` for a bilinear ``F`` equals a weighted sum of the
     five neighbour products ``Y_ij Y_i'j'`` (``|i-i'|, |j-j'| <= 1``) with weights
     ``G0^2, 2 G0 G1, 2 G1^2`` from the hat function sampled at ``m / upsample``, so no
     fine grid is ever stored. ``upsample=1`` is the plain pixel-level squared centroid.

   Both estimate the centre of the imaged ellipse. The image of a disc's centre differs
   from it by the perspective eccentricity (:mod:`fieldcal.field.eccentricity`), applied once a
   pose is known.

4. **Filters and quality figures**: size, roundness (minor / major), edge residual of the
   ellipse fit (squares and clutter fit badly), contrast and SNR, saturation, truncation at
   the image border; duplicates (two candidates on one blob) are merged.

The default method is the one that measured more accurately on rendered images (see
``bench/README_extract.md``): :data:`DEFAULT_METHOD`.

Pixel convention: docs/conventions.md section 1, the centre of the top-left pixel is ``(0, 0)``; the
pixel at row ``i``, column ``j`` of a window whose top-left pixel is ``(x0, y0)`` has its
centre at ``(u, v) = (x0 + j, y0 + i)``.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

import cv2
import numpy as np
import pyarrow as pa
from numpy.lib.stride_tricks import sliding_window_view
from scipy.spatial import cKDTree

from fieldcal.errors import ImageError, InputError
from fieldcal.model.camera import Sensor
from fieldcal.session.schemas import arrow_schema

__all__ = [
    "METHODS", "DEFAULT_METHOD", "POLARITIES", "detect_targets", "measure_image",
    "empty_measurements", "measurements_table", "estimate_noise_dn", "coarse_step",
    "opencv_blob_centres",
]

METHODS = ("ellipse", "centroid")
DEFAULT_METHOD = "ellipse"
"""Chosen by measured accuracy on rendered paper-like images (bench/README_extract.md)."""
POLARITIES = ("dark", "bright")

_GROW_PX = 2         # the centroid's support: region grown by this many pixels
_MARGIN_PX = 5       # window margin beyond the coarse extent: ring + blur tail + position error
_CLEAR_PX = 3.0      # the fitted outline must stay this far inside the window's ring
_CLASS_PX = 4        # window sizes are multiples of this (stacked batches of one size)
_BATCH_PIXELS = 1 << 20  # pixels per stacked batch of windows
_MIN_EDGE_POINTS = 8
_FIT_ITERATIONS = 1  # algebraic fit; re-fits with Sampson weights change nothing measurable
_MIN_BG_DN = 1.0     # a dark figure's background below this is taken as this (ratio signal)
_SIGMA_FLOOR_PX = 0.003


# --------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------
def _check_image(image) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise InputError(f"image must be a 2-D array (rows, columns), got shape {arr.shape}")
    if arr.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
        raise InputError(f"image must be uint8 or uint16, got {arr.dtype}")
    if min(arr.shape) < 8:
        raise InputError(f"image of {arr.shape[1]} x {arr.shape[0]} px is too small to measure")
    return arr


def _check_choice(name, value, allowed):
    if value not in allowed:
        raise InputError(f"{name} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")


def _check_positive(name, value, minimum=0.0):
    if not (isinstance(value, (int, float, np.floating, np.integer)) and np.isfinite(value)
            and value > minimum):
        raise InputError(f"{name} must be a number > {minimum}, got {value!r}")


# --------------------------------------------------------------------------------------
# stage 1: candidates on a strided sample of the image
# --------------------------------------------------------------------------------------
def estimate_noise_dn(image, *, n_rows: int = 32) -> float:
    """Standard deviation of the pixel noise [DN], robustly, from ``n_rows`` spread rows.

    The median absolute difference of horizontally adjacent pixels, ``/ (0.6745 sqrt 2)``:
    edges are a minority of the pairs, so they do not move the median. At least 0.3 DN (the
    quantisation noise of integer pixels).
    """
    arr = _check_image(image)
    rows = arr[:: max(1, arr.shape[0] // n_rows)]
    diff = np.abs(np.diff(rows.astype(np.int32), axis=1)).ravel()
    mad = float(np.median(diff)) if diff.size else 0.0
    return max(mad / (0.6745 * math.sqrt(2.0)), 0.3)


def coarse_step(min_diameter_px: float, psf_sigma_px: float = 1.0) -> int:
    """Sampling step of the candidate search [px] for discs of at least ``min_diameter_px``.

    A disc of diameter ``d`` holds a sample of a square lattice of pitch ``s`` in its flat
    interior (diameter ``d - 4 sigma``) whenever ``s sqrt 2 <= d - 4 sigma``.
    """
    inner = float(min_diameter_px) - 4.0 * psf_sigma_px
    return int(np.clip(math.floor(inner / math.sqrt(2.0)), 1, 16))


@dataclass
class _Candidates:
    u: np.ndarray        # (n,) first centre estimate [px]
    v: np.ndarray
    extent: np.ndarray   # (n,) upper bound of the blob's extent [px]


def _coarse_candidates(img, step, max_diameter_px, threshold_dn, sign, min_contrast_dn):
    """Candidates on the image sampled every ``step`` pixels; returns them and the contrast
    floor used (``min_contrast_dn``, or 2 % of the sample's 0.5-99.5 percentile range)."""
    off = step // 2
    sub = np.ascontiguousarray(img[off::step, off::step]) if step > 1 else img
    if min_contrast_dn is None:
        thin = sub[:: max(1, sub.shape[0] // 64), :: max(1, sub.shape[1] // 64)]
        lo, hi = np.percentile(thin, [0.5, 99.5])
        min_contrast_dn = 0.02 * float(hi - lo)
    k = int(math.ceil(max_diameter_px / step)) + 2
    k += 1 - k % 2
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    op = cv2.MORPH_BLACKHAT if sign < 0 else cv2.MORPH_TOPHAT
    hat = cv2.morphologyEx(sub, op, kernel, borderType=cv2.BORDER_REPLICATE)
    # the top-hat of pure noise is not centred on 0 (the closing picks local extremes):
    # measure from its median
    base = float(np.median(hat[:: max(1, hat.shape[0] // 128), :: max(1, hat.shape[1] // 128)]))
    thr = int(min(math.ceil(base + max(threshold_dn, 0.5 * min_contrast_dn)),
                  np.iinfo(img.dtype).max))
    binary = (hat > thr).view(np.uint8)
    n, labels = cv2.connectedComponents(binary, connectivity=8, ltype=cv2.CV_32S)
    # top-hat-weighted moments of each component (sums over its samples only)
    idx = np.flatnonzero(binary)
    lab = labels.ravel()[idx] - 1
    hv = hat.ravel()[idx].astype(np.float64) - base
    r, c = np.divmod(idx, sub.shape[1])
    m = n - 1

    def total(w):
        return np.bincount(lab, weights=w, minlength=m)

    sh = total(hv)
    with np.errstate(invalid="ignore", divide="ignore"):
        mc, mr = total(hv * c) / sh, total(hv * r) / sh
        dc, dr = c - mc[lab], r - mr[lab]
        vcc, vrr, vcr = total(hv * dc * dc) / sh, total(hv * dr * dr) / sh, total(hv * dc * dr) / sh
        peak = total(hv * hv) / sh
        # samples' worth of full contrast -> the area, and the diameter of a disc of that area
        d_est = 2.0 * step * np.sqrt(sh / peak / math.pi)
        # extent along the longest axis: 4 sigma (a disc's diameter; 1.15 x a bar's length)
        lam = 0.5 * (vcc + vrr) + np.sqrt(0.25 * (vcc - vrr) ** 2 + vcr**2)
        span = 4.0 * step * np.sqrt(lam)
    u, v = off + step * mc, off + step * mr
    extent = np.maximum(1.1 * d_est, span + 2.0)
    keep = (span <= max_diameter_px + 2 * step) & np.isfinite(u) & np.isfinite(v)
    cand = _Candidates(u[keep], v[keep], extent[keep])
    return cand, min_contrast_dn


# --------------------------------------------------------------------------------------
# point in polygon (exclusion zones such as ArUco markers)
# --------------------------------------------------------------------------------------
def _inside_any(u, v, polygons) -> np.ndarray:
    """Which points ``(u, v)`` lie inside any of ``polygons`` (list of (m, 2) arrays)."""
    inside = np.zeros(len(u), bool)
    for poly in polygons:
        p = np.asarray(poly, float).reshape(-1, 2)
        if len(p) < 3:
            raise InputError(f"exclude: a polygon needs at least 3 vertices, got {len(p)}")
        x1, y1 = p[:, 0], p[:, 1]
        x2, y2 = np.roll(x1, -1), np.roll(y1, -1)
        vv = v[:, None]
        crosses = (y1 > vv) != (y2 > vv)
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = x1 + (vv - y1) * (x2 - x1) / (y2 - y1)
        odd = np.sum(crosses & (u[:, None] < xs), axis=1) % 2 == 1
        inside |= odd
    return inside


# --------------------------------------------------------------------------------------
# stage 2/3: windows, stacked and measured together
# --------------------------------------------------------------------------------------
@functools.cache
def _ring(S: int):
    """The outer 1-pixel ring of an S x S window, in order round it: (i, j) indices (4S-4,)
    and the plane design (4S-4, 3) of ``bg = c0 + c1 g(j) + c2 g(i)``."""
    i = np.concatenate([np.zeros(S, int), np.arange(1, S), np.full(S - 1, S - 1), np.arange(S - 2, 0, -1)])
    j = np.concatenate([np.arange(S), np.full(S - 1, S - 1), np.arange(S - 2, -1, -1), np.zeros(S - 2, int)])
    g = _grid(S)
    A = np.stack([np.ones(i.size), g[j], g[i]], axis=1)
    return i, j, A


@functools.cache
def _grid(S: int):
    """Normalised window coordinate of pixel index 0..S-1 (the plane's variable), (S,)."""
    return (np.arange(S) - (S - 1) / 2.0) / S


@functools.cache
def _hat_sums(upsample):
    """``(G0, G1)``: sums of ``phi(x)^2`` and ``phi(x) phi(x - 1)`` over a grid of pitch 1/k.

    ``phi`` is the linear-interpolation hat; ``upsample=None`` gives the continuous limit
    (the integrals 2/3 and 1/6, scaled by any constant).
    """
    if upsample is None:
        return 2.0 / 3.0, 1.0 / 6.0
    k = int(upsample)
    m = np.arange(-(k - 1), k)
    s = np.arange(k + 1) / k
    return float(np.sum((1 - np.abs(m) / k) ** 2)), float(np.sum((1 - s) * s))


def _gather(img, y0, x0, S):
    """(n, S, S) copies of the windows with top-left pixels (x0, y0)."""
    return sliding_window_view(img, (S, S))[y0, x0]


@dataclass
class _Background:
    """Per-window background plane ``bg = c0 + c1 g(j) + c2 g(i)`` [DN] and the signal map.

    The signal is the figure's departure from the background, positive for the figure:
    ``sign (raw - bg)``; for a dark figure on a lit surface (``c0 > 0``) it is scaled by
    ``c0 / bg``, because such a figure's signal scales with the illumination like the
    background does: this removes the shading's tilt across the window (which would move a
    weighted centroid and the edge level) and keeps the unit DN at the window's centre.
    """

    coef: np.ndarray     # (n, 3)
    sign: int
    S: int

    def bg(self, i, j):
        """Background at window pixels (i, j) (arrays broadcasting against (n, ...))."""
        g = _grid(self.S)
        c = self.coef
        shape = (-1,) + (1,) * (np.ndim(i) - 1)
        return c[:, 0].reshape(shape) + c[:, 1].reshape(shape) * g[j] + c[:, 2].reshape(shape) * g[i]

    def signal(self, raw_vals, bg_vals):
        """Signal at pixels with values ``raw_vals`` where the background is ``bg_vals``."""
        raw_vals = np.asarray(raw_vals, np.float64)
        if self.sign < 0:
            c0 = self.coef[:, 0].reshape((-1,) + (1,) * (raw_vals.ndim - 1))
            return (bg_vals - raw_vals) * c0 / np.maximum(bg_vals, _MIN_BG_DN)
        return raw_vals - bg_vals


def _background(raw, sign, noise_dn):
    """Background plane and noise of each window from its outer ring (robust to intruders)."""
    n, S, _ = raw.shape
    i, j, A = _ring(S)
    R = raw.reshape(n, S * S)[:, i * S + j].astype(np.float64)            # (n, 4S-4)
    # noise: differences of neighbouring ring pixels. An edge crossing the ring gives a few
    # large ones: a mean absolute difference clipped at 5 sigma of the image-wide noise
    # ignores them (E|d| = 2 sigma / sqrt(pi) for independent Gaussian pixels)
    d = np.abs(np.diff(R, axis=1))
    clip = 5.0 * math.sqrt(2.0) * noise_dn
    keep = d < clip
    noise = (np.where(keep, d, 0.0).sum(axis=1) / np.maximum(keep.sum(axis=1), 1)) * (math.sqrt(math.pi) / 2)
    noise = np.maximum(noise, 0.3)
    # background: a plane fitted to the ring pixels within 4 noise of the ring's median
    # (what intrudes into the ring, a neighbour or the blob itself, is left out); the median
    # of 16 pixels spread round the ring
    med = np.median(R[:, :: max(1, R.shape[1] // 16)], axis=1)
    good = (np.abs(R - med[:, None]) < 4.0 * noise[:, None] + 0.02 * np.abs(med[:, None]))
    good = good.astype(np.float64)
    P6 = np.stack([A[:, 0], A[:, 1], A[:, 2], A[:, 1] ** 2, A[:, 1] * A[:, 2], A[:, 2] ** 2], 1)
    iu = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
    N = (good @ P6)[:, iu] + 1e-9 * np.eye(3)
    rhs = (good * R) @ A
    coef = np.linalg.solve(N, rhs[..., None])[..., 0]
    if sign < 0:
        coef[:, 0] = np.maximum(coef[:, 0], _MIN_BG_DN)
    return _Background(coef, sign, S), noise


def _signal_stack(raw, bgd: _Background):
    """The signal (n, S, S) float32 of whole windows (the centroid method needs it)."""
    n, S, _ = raw.shape
    g = _grid(S).astype(np.float32)
    c = bgd.coef.astype(np.float32)
    bg = c[:, 0, None, None] + c[:, 1, None, None] * g[None, None, :] + c[:, 2, None, None] * g[None, :, None]
    Y = raw.astype(np.float32)
    if bgd.sign > 0:
        Y -= bg
    else:                       # c0 (bg - raw) / bg
        np.divide(Y, np.maximum(bg, np.float32(_MIN_BG_DN)), out=Y)
        np.subtract(1.0, Y, out=Y)
        Y *= c[:, 0, None, None]
    return Y


def _isodata(Y, contrast, max_iter=8):
    """The paper's iterative threshold per window (start at the mean; mean of the two class
    means; repeat), kept within [0.3, 0.7] of the figure's level."""
    n = Y.shape[0]
    flat = Y.reshape(n, -1)
    total = flat.sum(axis=1, dtype=np.float64)
    N = flat.shape[1]
    t = total / N
    for _ in range(max_iter):
        above = flat > t[:, None].astype(np.float32)
        n1 = np.count_nonzero(above, axis=1)
        s1 = np.einsum("ij,ij->i", flat, above.view(np.uint8).astype(np.float32), dtype=np.float64)
        t_new = 0.5 * (s1 / np.maximum(n1, 1) + (total - s1) / np.maximum(N - n1, 1))
        done = np.all(np.abs(t_new - t) <= 1e-3 * contrast)
        t = t_new
        if done:
            break
    return np.clip(t, 0.3 * contrast, 0.7 * contrast)


def _measure_windows(img, y0, x0, su, sv, S, *, sign, step, method, upsample, sat_level,
                     noise_dn):
    """Measure one stack of same-size windows. Returns a dict of (n,) arrays.

    ``su, sv``: candidate position in window coordinates; ``y0, x0``: window origins.
    """
    H, W = img.shape
    n = len(y0)
    ar = np.arange(n)
    raw = _gather(img, y0, x0, S)
    bgd, noise = _background(raw, sign, noise_dn)
    g = _grid(S)

    # the extreme pixel near the candidate, and the figure's level (3 x 3 mean there)
    B = min(S, 2 * (step // 2 + 1) + 1)
    by = np.clip(np.rint(sv).astype(int) - B // 2, 0, S - B)
    bx = np.clip(np.rint(su).astype(int) - B // 2, 0, S - B)
    flat = raw.reshape(-1)
    base = (ar * (S * S))[:, None, None]
    ii = by[:, None, None] + np.arange(B)[None, :, None]
    jj = bx[:, None, None] + np.arange(B)[None, None, :]
    box = bgd.signal(flat.take(base + ii * S + jj), bgd.bg(ii, jj)).reshape(n, B * B)
    arg = np.argmax(box, axis=1)
    sy, sx = by + arg // B, bx + arg % B
    pi = np.clip(sy - 1, 0, S - 3)[:, None, None] + np.arange(3)[None, :, None]
    pj = np.clip(sx - 1, 0, S - 3)[:, None, None] + np.arange(3)[None, None, :]
    contrast = bgd.signal(flat.take(base + pi * S + pj), bgd.bg(pi, pj)).mean(axis=(1, 2))
    contrast = np.maximum(contrast, 1e-6)

    # threshold and the mask of pixels beyond it, written into a column of windows separated
    # by empty rows (one connected-components call labels them all)
    pad = _GROW_PX + 1
    M = np.zeros((n, S + pad, S), np.uint8)
    Mv = M[:, :S, :].view(bool)
    Y = None
    if method == "centroid":
        Y = _signal_stack(raw, bgd)
        t = _isodata(Y, contrast)
        np.greater(Y, t[:, None, None].astype(np.float32), out=Mv)
    else:
        t = 0.5 * contrast
        c = bgd.coef
        if sign < 0:           # figure where c0 (bg - raw) / bg > t: raw < bg (1 - t / c0)
            k = 1.0 - t / c[:, 0]
            T = (c[:, 0] * k)[:, None, None] + (c[:, 1] * k)[:, None, None] * g[None, None, :]
            T = T.astype(np.float32) + ((c[:, 2] * k)[:, None, None] * g[None, :, None]).astype(np.float32)
            np.less(raw, T, out=Mv)
        else:                  # figure where raw > bg + t
            T = ((c[:, 0] + t)[:, None, None] + c[:, 1, None, None] * g[None, None, :]).astype(np.float32) \
                + (c[:, 2, None, None] * g[None, :, None]).astype(np.float32)
            np.greater(raw, T, out=Mv)
        del T

    # region growing: the 8-connected component beyond the threshold holding the seed
    _, labels = cv2.connectedComponents(M.reshape(n * (S + pad), S), connectivity=8,
                                        ltype=cv2.CV_32S)
    labels = labels.reshape(n, S + pad, S)[:, :S, :]
    seed_label = labels[ar, sy, sx]
    region = labels == seed_label[:, None, None]
    region &= (seed_label > 0)[:, None, None]
    del labels, M

    # the region's outline: first and last region pixel of every row and column
    # (argmax finds the first True fast along a contiguous axis: the columns are scanned in
    # a transposed copy, the last True in copies flipped by OpenCV)
    regionT = np.ascontiguousarray(region.transpose(0, 2, 1))
    L = np.argmax(region, axis=2)                       # (n, S) over rows i
    Rr = S - 1 - np.argmax(_flip_rows(region), axis=2)
    T_ = np.argmax(regionT, axis=2)                     # (n, S) over columns j
    Bc = S - 1 - np.argmax(_flip_rows(regionT), axis=2)
    rows = np.broadcast_to(np.arange(S), (n, S))
    row_has = region[ar[:, None], rows, L]
    col_has = region[ar[:, None], T_, rows]
    touch_l, touch_r = (row_has & (L == 0)).any(axis=1), (row_has & (Rr == S - 1)).any(axis=1)
    touch_t, touch_b = (col_has & (T_ == 0)).any(axis=1), (col_has & (Bc == S - 1)).any(axis=1)
    at_t, at_b, at_l, at_r = y0 == 0, y0 + S == H, x0 == 0, x0 + S == W
    truncated = (touch_t & at_t) | (touch_b & at_b) | (touch_l & at_l) | (touch_r & at_r)
    overflow = (touch_t & ~at_t) | (touch_b & ~at_b) | (touch_l & ~at_l) | (touch_r & ~at_r)
    area = np.where(row_has, Rr - L + 1, 0).sum(axis=1).astype(float)   # of the row spans

    # sub-pixel edge points: where the signal crosses t between the outermost region pixel
    # and its outside neighbour, on every row (left, right) and column (top, bottom)
    px, py, valid = _outline_points(raw, bgd, t, rows, L, Rr, T_, Bc, row_has, col_has, S)
    fit = _fit_ellipses(px, py, valid)

    # the fitted outline must keep clear of the ring (else the background took in the blur
    # tail): a window found too tight is measured again, larger
    ca, sa = np.cos(np.radians(fit["angle_deg"])), np.sin(np.radians(fit["angle_deg"]))
    hx = np.sqrt((fit["ea"] * ca) ** 2 + (fit["eb"] * sa) ** 2) + _CLEAR_PX
    hy = np.sqrt((fit["ea"] * sa) ** 2 + (fit["eb"] * ca) ** 2) + _CLEAR_PX
    with np.errstate(invalid="ignore"):
        tight = (((fit["eu"] - hx < 1) & ~at_l) | ((fit["eu"] + hx > S - 2) & ~at_r)
                 | ((fit["ev"] - hy < 1) & ~at_t) | ((fit["ev"] + hy > S - 2) & ~at_b))

    saturated = raw.max(axis=(1, 2)) >= sat_level
    if sign < 0:
        saturated |= raw.min(axis=(1, 2)) == 0

    out = {"noise": noise, "contrast": contrast, "area": area, "truncated": truncated,
           "overflow": overflow, "tight": tight, "saturated": saturated, "threshold": t}
    out.update(fit)
    if method == "centroid":
        support = cv2.dilate(region.view(np.uint8).reshape(n * S, S),
                             cv2.getStructuringElement(cv2.MORPH_RECT, (2 * _GROW_PX + 1,) * 2))
        support = support.reshape(n, S, S).view(bool)
        # the dilation may reach from one window into the next along the column: cut it
        support[:, :_GROW_PX] &= _spill_ok(region, _GROW_PX, top=True)
        support[:, -_GROW_PX:] &= _spill_ok(region, _GROW_PX, top=False)
        out["cu"], out["cv"] = _squared_centroid(Y, support, upsample)
    else:
        out["cu"], out["cv"] = fit["eu"], fit["ev"]
    out["cu"] = out["cu"] + x0
    out["cv"] = out["cv"] + y0
    return out


def _flip_rows(mask):
    """``mask[:, :, ::-1]`` as a contiguous copy (bool (n, S, S))."""
    n, a, b = mask.shape
    return cv2.flip(mask.view(np.uint8).reshape(n * a, b), 1).reshape(n, a, b).view(bool)


def _outline_points(raw, bgd, t, rows, L, Rr, T_, Bc, row_has, col_has, S):
    """Edge points (n, 4S) [window px] at level ``t`` on the outline of each region.

    For every row the first and last region pixel (left, right) and for every column the
    first and last (top, bottom): the edge lies between that pixel (signal above ``t``)
    and its outside neighbour (not above ``t``), where the linear interpolation of the
    signal crosses ``t``.
    """
    n = raw.shape[0]
    c = bgd.coef.astype(np.float32)
    g = _grid(S).astype(np.float32)
    flat = raw.reshape(-1)
    base = (np.arange(n) * (S * S))[:, None]
    tt = t.astype(np.float32)[:, None]
    inv_s = np.float32(1.0 / S)
    # the four sides: (row index, column index, step to the outside pixel (di, dj))
    sides = ((rows, L, 0, -1), (rows, Rr, 0, 1), (T_, rows, -1, 0), (Bc, rows, 1, 0))
    px, py = [], []
    for i_in, j_in, di, dj in sides:
        i_out = np.clip(i_in + di, 0, S - 1)
        j_out = np.clip(j_in + dj, 0, S - 1)
        bg_in = c[:, 0:1] + c[:, 1:2] * g[j_in] + c[:, 2:3] * g[i_in]
        bg_out = bg_in + (c[:, 1:2] * (dj * inv_s) + c[:, 2:3] * (di * inv_s))
        r_in = flat.take(base + i_in * S + j_in).astype(np.float32)
        r_out = flat.take(base + i_out * S + j_out).astype(np.float32)
        if bgd.sign < 0:          # c0 (bg - raw) / bg, see _Background
            s_in = c[:, 0:1] * (1.0 - r_in / np.maximum(bg_in, _MIN_BG_DN))
            s_out = c[:, 0:1] * (1.0 - r_out / np.maximum(bg_out, _MIN_BG_DN))
        else:
            s_in, s_out = r_in - bg_in, r_out - bg_out
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.clip((s_in - tt) / (s_in - s_out), 0.0, 1.0)    # from the inside pixel
        f = np.nan_to_num(f, nan=0.5).astype(np.float64)
        # the point moves from its inside pixel towards the outside one by f
        px.append(j_in + dj * f)
        py.append(i_in + di * f)
    valid = np.concatenate([row_has & (L >= 1), row_has & (Rr <= S - 2),
                            col_has & (T_ >= 1), col_has & (Bc <= S - 2)], axis=1)
    return np.concatenate(px, axis=1), np.concatenate(py, axis=1), valid


def _spill_ok(region, g, *, top):
    """Mask of the first (last) ``g`` rows of each window: False where the dilation of the
    neighbouring window in the stacked column could have reached them."""
    n = region.shape[0]
    ok = np.ones((n, g, 1), bool)
    if top:
        spill = region[:-1, -g:, :].any(axis=(1, 2))
        ok[1:, :, 0] = ~spill[:, None]
    else:
        spill = region[1:, :g, :].any(axis=(1, 2))
        ok[:-1, :, 0] = ~spill[:, None]
    return ok


def _squared_centroid(Y, support, upsample):
    """Grey centroid with squared weights of the bilinear interpolant (see the module docstring).

    Returns window coordinates ``(u, v)`` (n,) of the centre.
    """
    Wt = np.where(support, np.maximum(Y, 0.0), 0.0).astype(np.float32)
    S = Wt.shape[1]
    G0, G1 = _hat_sums(upsample)
    j = np.arange(S, dtype=np.float64)
    jh = j[:-1] + 0.5
    terms = [  # (product, weight, column coordinates, row coordinates)
        (Wt * Wt, G0 * G0, j, j),
    ]
    if G1 > 0:
        terms += [
            (Wt[:, :, :-1] * Wt[:, :, 1:], 2 * G0 * G1, jh, j),
            (Wt[:, :-1, :] * Wt[:, 1:, :], 2 * G0 * G1, j, jh),
            (Wt[:, :-1, :-1] * Wt[:, 1:, 1:], 2 * G1 * G1, jh, jh),
            (Wt[:, :-1, 1:] * Wt[:, 1:, :-1], 2 * G1 * G1, jh, jh),
        ]
    s0 = su = sv = 0.0
    for P, w, cj, ci in terms:
        colsum = P.sum(axis=1, dtype=np.float64)     # (n, columns)
        rowsum = P.sum(axis=2, dtype=np.float64)     # (n, rows)
        s0 = s0 + w * colsum.sum(axis=1)
        su = su + w * (colsum @ cj)
        sv = sv + w * (rowsum @ ci)
    with np.errstate(invalid="ignore", divide="ignore"):
        return su / s0, sv / s0


def _fit_ellipses(px, py, valid):
    """Fit one ellipse to the valid points of each row of ``px, py`` (n, K) [px].

    Algebraic conic ``F = a x^2 + b xy + c y^2 + d x + e y + f`` with the Euclidean-invariant
    constraint ``a + c = 1`` (coordinates centred and scaled per window); with
    ``_FIT_ITERATIONS > 1`` re-fits weighted by ``1 / |grad F|^2`` (Sampson's approximation
    of the geometric distance), which moved no centre measurably in the tests (ellipses down
    to 0.3 roundness), so one fit is the default. ``edge_rms`` is the RMS Sampson distance.
    Returns the centre ``eu, ev``, semi-axes ``ea >= eb``, ``angle_deg`` of the major axis,
    ``edge_rms`` (RMS Sampson distance [px]), ``n_edge`` and ``fit_ok``, each (n,).
    """
    counts = valid.sum(axis=1)
    cnt = np.maximum(counts, 1)
    vf = valid.astype(np.float64)
    mx = (px * vf).sum(axis=1) / cnt
    my = (py * vf).sum(axis=1) / cnt
    xn = np.where(valid, px - mx[:, None], 0.0)
    yn = np.where(valid, py - my[:, None], 0.0)
    scale = np.sqrt((xn**2 + yn**2).sum(axis=1) / cnt) + 1e-12
    xn = (xn / scale[:, None]).astype(np.float32)
    yn = (yn / scale[:, None]).astype(np.float32)
    vf = vf.astype(np.float32)
    # unknowns (c, b, d, e, f) of F = (1 - c) x^2 + b xy + c y^2 + d x + e y + f; rhs -x^2.
    # Normalised coordinates are O(1), so float32 sums over ~100 points lose nothing that
    # matters (1e-6 relative); the 5 x 5 solves are in float64.
    D = np.stack([yn * yn - xn * xn, xn * yn, xn, yn, vf], axis=1)     # (n, 5, K)
    rhs = (-(xn * xn))[:, :, None]
    wt = None
    ok = counts >= _MIN_EDGE_POINTS
    eye = np.eye(5)
    for it in range(_FIT_ITERATIONS):
        Dw = D * wt[:, None, :] if it else D
        N = np.matmul(Dw, D.transpose(0, 2, 1)).astype(np.float64) + 1e-12 * eye
        r = np.matmul(Dw, rhs).astype(np.float64)
        N[~ok] = eye
        r[~ok] = 0.0
        theta = np.linalg.solve(N, r)[..., 0]
        cc, bb, dd, ee = theta[:, 0], theta[:, 1], theta[:, 2], theta[:, 3]
        aa = 1.0 - cc
        gx = (2 * aa[:, None]) * xn + bb[:, None] * yn + dd[:, None]
        gy = bb[:, None] * xn + (2 * cc[:, None]) * yn + ee[:, None]
        wt = np.where(valid, 1.0 / np.maximum(gx * gx + gy * gy, 1e-12), 0.0).astype(np.float32)
    cc, bb, dd, ee, ff = theta.T
    aa = 1.0 - cc
    F = (aa[:, None] * xn + bb[:, None] * yn + dd[:, None]) * xn \
        + (cc[:, None] * yn + ee[:, None]) * yn + ff[:, None]
    rms = np.sqrt((F * F * wt).sum(axis=1) / cnt) * scale          # Sampson distances [px]

    det = 4 * aa * cc - bb**2
    ok &= det > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        x0 = (bb * ee - 2 * cc * dd) / det
        y0 = (bb * dd - 2 * aa * ee) / det
        F0 = aa * x0**2 + bb * x0 * y0 + cc * y0**2 + dd * x0 + ee * y0 + ff
        tr, dif = aa + cc, np.sqrt((aa - cc) ** 2 + bb**2)
        lam1, lam2 = (tr - dif) / 2, (tr + dif) / 2        # lam1 <= lam2: major axis along lam1
        ea = np.sqrt(-F0 / lam1) * scale
        eb = np.sqrt(-F0 / lam2) * scale
        ang = 0.5 * np.degrees(np.arctan2(bb, aa - cc)) + 90.0
    ok &= np.isfinite(ea) & np.isfinite(eb) & (lam1 > 0)
    nan = np.nan
    return {
        "eu": np.where(ok, mx + x0 * scale, nan), "ev": np.where(ok, my + y0 * scale, nan),
        "ea": np.where(ok, ea, nan), "eb": np.where(ok, eb, nan),
        "angle_deg": np.where(ok, np.mod(ang, 180.0), nan), "edge_rms": np.where(ok, rms, nan),
        "n_edge": counts.astype(float), "fit_ok": ok,
    }


def _window_size(extent):
    need = np.asarray(extent) + 2 * _MARGIN_PX
    return (_CLASS_PX * np.ceil(need / _CLASS_PX)).astype(int)


def _measure_all(img, cand: _Candidates, *, sign, step, method, upsample, sat_level,
                 max_diameter_px, min_snr, noise_dn):
    """Measure every candidate; windows too small for their blob are measured again, larger."""
    H, W = img.shape
    S_cap = min(H, W)
    S = np.minimum(_window_size(cand.extent), S_cap)
    u, v = cand.u.copy(), cand.v.copy()
    results = []
    todo = np.arange(len(u))
    for attempt in range(2):
        next_todo, next_S = [], []
        batches = []
        for size in np.unique(S[todo]):
            same = todo[S[todo] == size]
            # batches of windows small enough for the CPU caches (every stage streams them)
            per = max(16, _BATCH_PIXELS // int(size) ** 2)
            batches += [(size, same[k:k + per]) for k in range(0, same.size, per)]
        for size, idx in batches:
            y0 = np.clip(np.rint(v[idx]).astype(int) - size // 2, 0, H - size)
            x0 = np.clip(np.rint(u[idx]).astype(int) - size // 2, 0, W - size)
            r = _measure_windows(img, y0, x0, u[idx] - x0, v[idx] - y0, int(size), sign=sign,
                                 step=step, method=method, upsample=upsample, sat_level=sat_level,
                                 noise_dn=noise_dn)
            r["index"] = idx
            retry = ((r["overflow"] | r["tight"]) & (size < S_cap) & (attempt == 0)
                     & (r["contrast"] >= min_snr * r["noise"]))
            bigger = min(S_cap, int(_CLASS_PX * math.ceil(
                min(1.5 * size + 8, max_diameter_px + 2 * _MARGIN_PX + 2 * step) / _CLASS_PX)))
            if bigger <= size:
                retry[:] = False
            if retry.any():
                # re-centre on what was measured, where it was
                cu, cv = r["cu"][retry], r["cv"][retry]
                fin = np.isfinite(cu) & np.isfinite(cv)
                u[idx[retry][fin]], v[idx[retry][fin]] = cu[fin], cv[fin]
                next_todo.append(idx[retry])
                next_S.append(np.full(retry.sum(), bigger))
            results.append({k: val[~retry] for k, val in r.items()})
        if not next_todo:
            break
        todo = np.concatenate(next_todo)
        S = S.copy()
        S[todo] = np.concatenate(next_S)
    if not results:
        return {}
    return {k: np.concatenate([r[k] for r in results]) for k in results[0]}


# --------------------------------------------------------------------------------------
# precision and the table
# --------------------------------------------------------------------------------------
def _apriori_sigma(snr, diameter_px, psf_sigma_px=0.8):
    """A-priori one-sigma precision of a disc's centre, per axis [px], from SNR and size.

    The Cramer-Rao bound of a disc's position in white noise: an edge blurred by
    ``s = sqrt(sigma_psf^2 + 1/12)`` (PSF and pixel) has ``sum (dI/dr)^2 = C^2 / (2 sqrt(pi) s)``
    per unit length; over the rim ``pi d``, half of it along each axis, so
    ``sigma = sqrt(4 sqrt(pi) s / (pi d)) / snr``; combined with a floor of 0.003 px for what
    the model leaves out (rendering tests measure 0.003-0.004 px without noise).
    """
    s = math.sqrt(psf_sigma_px**2 + 1.0 / 12.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sig = np.sqrt(4.0 * math.sqrt(math.pi) * s / (math.pi * np.maximum(diameter_px, 1.0)))
        sig = sig / np.maximum(snr, 1e-6)
    return np.hypot(sig, _SIGMA_FLOOR_PX)


def empty_measurements() -> pa.Table:
    """A table of schema ``measurements`` with no rows."""
    return arrow_schema("measurements").empty_table()


def measurements_table(columns: dict, image_name: str = "") -> pa.Table:
    """A ``measurements`` table from a dict of columns (missing nullable columns are null)."""
    schema = arrow_schema("measurements")
    n = len(columns["u_px"])
    cols = {}
    for f in schema:
        if f.name == "image":
            cols["image"] = pa.repeat(pa.scalar(image_name, pa.string()), n)
        elif f.name == "blob":
            cols["blob"] = pa.array(np.arange(n, dtype=np.int32))
        elif f.name in columns:
            val = columns[f.name]
            if isinstance(val, (pa.Array, pa.ChunkedArray)):
                cols[f.name] = val.cast(f.type) if val.type != f.type else val
            elif isinstance(val, np.ndarray) and val.dtype.kind == "f" and f.nullable:
                cols[f.name] = pa.array(val, f.type, mask=~np.isfinite(val))
            else:
                cols[f.name] = pa.array(val, f.type)
        elif f.nullable:
            cols[f.name] = pa.nulls(n, f.type)
        else:
            raise InputError(f"measurements: column {f.name!r} is required")
    return pa.table(cols, schema=schema)


def _dedupe(u, v, radius, score):
    """Indices to keep when several measurements fall on one blob (closest pairs merged)."""
    keep = np.ones(len(u), bool)
    if len(u) < 2:
        return keep
    tree = cKDTree(np.stack([u, v], axis=1))
    pairs = tree.query_pairs(r=float(np.nanmax(radius)), output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        close = np.hypot(u[i] - u[j], v[i] - v[j]) < np.minimum(radius[i], radius[j])
        i, j = i[close], j[close]
        loser = np.where(score[i] >= score[j], j, i)
        keep[loser] = False
    return keep


# --------------------------------------------------------------------------------------
# public
# --------------------------------------------------------------------------------------
def detect_targets(image, *, polarity: str = "dark", min_diameter_px: float = 8.0,
                   max_diameter_px: float = 64.0, method: str = DEFAULT_METHOD,
                   exclude=None, min_snr: float = 8.0, min_contrast: float | None = None,
                   min_roundness: float = 0.3,
                   max_edge_rms_px: float | None = None, upsample: int | None = 4,
                   saturation_level: int | None = None, psf_sigma_px: float = 0.8,
                   image_name: str = "", return_rejected: bool = False) -> pa.Table:
    """Find circular targets in an image and measure their centres to sub-pixel accuracy.

    Parameters
    ----------
    image : (H, W) uint8 or uint16 ndarray
        The pixels [DN]; never copied or converted as a whole.
    polarity : {"dark", "bright"}
        Dark discs on a light background (the session's ``target_polarity``) or the reverse.
    min_diameter_px, max_diameter_px : float
        The range of disc diameters to look for [px]. ``min_diameter_px`` sets the sampling
        step of the candidate search (:func:`coarse_step`): larger is faster.
    method : {"ellipse", "centroid"}
        How the centre is measured (module docstring); default :data:`DEFAULT_METHOD`.
    exclude : sequence of (m, 2) arrays, optional
        Polygons [px] to skip (e.g. the outlines of detected ArUco markers).
    min_snr : float
        Smallest accepted contrast over background noise.
    min_contrast : float, optional
        Smallest accepted contrast [DN]; default 2 % of the image's range (0.5 to 99.5
        percentile of a sample), which keeps shading and texture out of a noise-free image.
    min_roundness : float
        Smallest accepted minor / major axis ratio (0.3: discs seen up to ~70 deg off-normal).
    max_edge_rms_px : float, optional
        Largest accepted RMS distance of the edge points from the fitted ellipse [px];
        default twice the expected scatter of an edge point (from the SNR and the blur) plus
        ``0.05 + 0.01 diameter`` (a disc measures about the scatter, a square ~5 % of its size).
    upsample : int or None
        ``"centroid"`` only: the bilinear interpolation factor (None: the continuous limit,
        1: pixel-level squared centroid).
    saturation_level : int, optional
        Pixel value counted as saturated (default the dtype's maximum).
    psf_sigma_px : float
        The expected blur [px], used for the search step and the a-priori sigma.
    image_name : str
        Written to the ``image`` column.
    return_rejected : bool
        For diagnosis: also return rejected candidates, with a ``reject`` column naming
        the first filter that failed (not part of the ``measurements`` schema).

    Returns
    -------
    pyarrow.Table
        Schema ``measurements`` (``schemas/measurements.arrow.json``), one row per target,
        ``kind = "disc"``; positions in the pixel convention of docs/conventions.md section 1.
    """
    img = _check_image(image)
    _check_choice("polarity", polarity, POLARITIES)
    _check_choice("method", method, METHODS)
    _check_positive("min_diameter_px", min_diameter_px, 1.0)
    _check_positive("max_diameter_px", max_diameter_px, 1.0)
    if max_diameter_px < min_diameter_px:
        raise InputError(f"max_diameter_px ({max_diameter_px}) is smaller than min_diameter_px "
                         f"({min_diameter_px})")
    _check_positive("min_snr", min_snr)
    if upsample is not None and not (isinstance(upsample, (int, np.integer)) and 1 <= upsample <= 64):
        raise InputError(f"upsample must be an integer in 1..64 or None, got {upsample!r}")
    sign = -1 if polarity == "dark" else 1
    sat_level = np.iinfo(img.dtype).max if saturation_level is None else int(saturation_level)

    noise_dn = estimate_noise_dn(img)
    step = coarse_step(min_diameter_px, psf_sigma_px)
    thr = max(0.5 * min_snr, 5.0) * noise_dn
    cand, min_contrast_dn = _coarse_candidates(img, step, max_diameter_px, thr, sign, min_contrast)
    if exclude is not None and len(cand.u):
        inside = _inside_any(cand.u, cand.v, list(exclude))
        cand = _Candidates(cand.u[~inside], cand.v[~inside], cand.extent[~inside])
    if len(cand.u) == 0:
        return empty_measurements()
    r = _measure_all(img, cand, sign=sign, step=step, method=method, upsample=upsample,
                     sat_level=sat_level, max_diameter_px=max_diameter_px, min_snr=min_snr,
                     noise_dn=noise_dn)

    major, minor = 2 * r["ea"], 2 * r["eb"]
    diameter = 2 * np.sqrt(r["ea"] * r["eb"])
    snr = r["contrast"] / r["noise"]
    sigma = _apriori_sigma(snr, diameter, psf_sigma_px)
    # an edge point's expected scatter: noise over the edge's slope C / (sqrt(2 pi) s)
    edge_noise = math.sqrt(2 * math.pi) * math.sqrt(psf_sigma_px**2 + 1 / 12) / np.maximum(snr, 1e-6)
    if max_edge_rms_px is None:
        # discs measure 0.7-1.3 x edge_noise; a square ~0.05 of its size
        max_rms = 2.0 * edge_noise + 0.01 * np.nan_to_num(diameter) + 0.05
    else:
        max_rms = np.full(len(snr), float(max_edge_rms_px))
    checks = [
        ("overflow", r["overflow"]),
        ("no fit", ~r["fit_ok"] | ~np.isfinite(r["cu"]) | ~np.isfinite(r["cv"])),
        ("snr", ~(snr >= min_snr)),
        ("contrast", ~(r["contrast"] >= min_contrast_dn)),
        ("small", ~(diameter >= min_diameter_px)),
        ("large", ~(diameter <= max_diameter_px)),
        ("roundness", ~(minor >= min_roundness * major)),
        ("shape", ~(r["edge_rms"] <= max_rms)),
    ]
    reasons = [""] + [name for name, _ in checks] + ["excluded", "duplicate"]
    reject = np.zeros(len(snr), np.int8)            # index into reasons; 0: accepted
    for code, (_, bad) in enumerate(checks, start=1):
        reject[(reject == 0) & bad] = code
    ok = reject == 0
    if exclude is not None:
        ins = _inside_any(np.nan_to_num(r["cu"]), np.nan_to_num(r["cv"]), list(exclude))
        reject[ok & ins] = reasons.index("excluded")
        ok = reject == 0
    k = np.flatnonzero(ok)
    dup = ~_dedupe(r["cu"][k], r["cv"][k], 0.5 * diameter[k], snr[k])
    reject[k[dup]] = reasons.index("duplicate")
    ok = reject == 0
    sel = np.flatnonzero(ok | return_rejected)
    sel = sel[np.lexsort((r["cu"][sel], np.round(r["cv"][sel] / 4.0)))] if sel.size else sel
    cols = {
        "kind": pa.repeat(pa.scalar("disc"), sel.size),
        "code": pa.nulls(sel.size, pa.int32()),
        "u_px": r["cu"][sel], "v_px": r["cv"][sel], "sigma_px": sigma[sel],
        "diameter_px": diameter[sel], "major_px": major[sel], "minor_px": minor[sel],
        "angle_deg": r["angle_deg"][sel], "roundness": (minor / major)[sel],
        "edge_rms_px": r["edge_rms"][sel], "contrast": r["contrast"][sel], "snr": snr[sel],
        "saturated": r["saturated"][sel], "truncated": r["truncated"][sel],
        "method": pa.repeat(pa.scalar(method), sel.size),
    }
    if return_rejected:
        for k in ("u_px", "v_px", "sigma_px", "diameter_px", "contrast", "snr"):
            cols[k] = np.nan_to_num(np.asarray(cols[k], float), nan=-1.0)
        table = measurements_table(cols, image_name)
        return table.append_column("reject", pa.array(np.asarray(reasons)[reject[sel]]))
    return measurements_table(cols, image_name)


def measure_image(path, *, polarity: str = "dark", sensor: Sensor | None = None,
                  coded: dict | None = None, name: str | None = None, **detect_kw) -> pa.Table:
    """Read one session image and measure its targets: ArUco markers and discs.

    Parameters
    ----------
    path : str or path-like
        The TIFF file (read with :func:`fieldcal.measure.imageio.read_image`).
    polarity : {"dark", "bright"}
        The session's ``target_polarity``.
    sensor : Sensor, optional
        The session's sensor; an image of another size is an error.
    coded : dict, optional
        The session's ``field.coded`` (``{"type": "aruco", "dictionary": ...}``); when given,
        markers are detected first and discs inside them are not reported.
    name : str, optional
        The image's name in the session (``images/x.tif``); default the path with forward
        slashes.
    **detect_kw
        Passed to :func:`detect_targets` (diameter range, method, filters).

    Returns
    -------
    pyarrow.Table
        Schema ``measurements``: the markers (``kind="aruco"``) then the discs, ``blob``
        numbered through.

    Raises
    ------
    ImageError
        The file is missing, corrupt, unsupported or of the wrong size, blank (every pixel
        the same: all black, saturated) or over-exposed (more than
        :data:`MAX_SATURATED_FRACTION` of the pixels at the sample type's maximum); one
        line naming it.
    """
    from fieldcal.measure.coded import detect_aruco, marker_exclusion_polygons
    from fieldcal.measure.imageio import read_image

    where = os.fspath(path)
    image_name = name if name is not None else where.replace(os.sep, "/")
    expect = None if sensor is None else (sensor.width_px, sensor.height_px)
    pixels = read_image(path, expect_size=expect)
    _check_exposure(pixels, where)
    tables = []
    exclude = list(detect_kw.pop("exclude", None) or [])
    try:
        if coded is not None:
            if coded.get("type", "aruco") != "aruco":
                raise InputError(f"coded targets of type {coded.get('type')!r} are not supported "
                                 "(only 'aruco')")
            markers = detect_aruco(pixels, dictionary=coded.get("dictionary", "DICT_4X4_1000"),
                                   image_name=image_name)
            tables.append(markers)
            exclude += marker_exclusion_polygons(markers)
        discs = detect_targets(pixels, polarity=polarity, exclude=exclude or None,
                               image_name=image_name, **detect_kw)
        tables.append(discs)
    except (cv2.error, MemoryError, FloatingPointError, np.linalg.LinAlgError) as err:
        msg = str(err).strip().splitlines()
        raise ImageError(f"cannot measure targets ({type(err).__name__}: "
                         f"{msg[0][:160] if msg else ''})", where) from None
    table = pa.concat_tables(tables) if tables else empty_measurements()
    return table.set_column(table.schema.get_field_index("blob"), "blob",
                            pa.array(np.arange(table.num_rows, dtype=np.int32)))


MAX_SATURATED_FRACTION = 0.5
"""An image with more of its pixels at the sample type's maximum is refused as over-exposed."""


def _check_exposure(pixels: np.ndarray, where: str) -> None:
    """Refuse an image with nothing to measure: blank (one value) or mostly saturated.

    Raises :class:`ImageError` naming the file; a measurement of such an image would only be
    an empty table, left out later with a misleading reason.
    """
    top = np.iinfo(pixels.dtype).max
    lo, hi = int(pixels.min()), int(pixels.max())
    if lo == hi:
        what = "all black" if hi == 0 else "saturated" if hi == top else "no contrast"
        raise ImageError(f"blank image: every pixel is {hi} ({what}); nothing to measure", where)
    if hi == top:
        share = np.count_nonzero(pixels == top) / pixels.size
        if share > MAX_SATURATED_FRACTION:
            raise ImageError(f"over-exposed: {100 * share:.0f} % of the pixels are saturated at {top}",
                             where)


def opencv_blob_centres(image, *, polarity: str = "dark") -> np.ndarray:
    """Centres (n, 2) [px] found by ``cv2.SimpleBlobDetector`` with its default settings.

    The peer that :func:`detect_targets` is compared with (tests, bench). A 16-bit image
    is first stretched to 8 bits (:func:`fieldcal.measure.coded.to_uint8`), which the detector
    needs; ``blobColor`` follows ``polarity``, every other setting is OpenCV's default.
    OpenCV's keypoints use the same pixel convention as docs/conventions.md section 1.
    """
    from fieldcal.measure.coded import to_uint8

    _check_choice("polarity", polarity, POLARITIES)
    img8 = to_uint8(_check_image(image))
    params = cv2.SimpleBlobDetector_Params()
    params.blobColor = 0 if polarity == "dark" else 255
    det = cv2.SimpleBlobDetector_create(params)
    kps = det.detect(img8)
    return np.array([k.pt for k in kps], float).reshape(-1, 2)
