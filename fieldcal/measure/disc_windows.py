"""Stage 3 of the disc detector, the NumPy reference: measure stacked windows together.

The procedure is the one of :mod:`fieldcal.measure.discs` (its module docstring, step 3):
per window a background plane from the outer ring, the figure's level, the threshold, the
8-connected region holding the extreme pixel, sub-pixel edge points on its outline, a conic
fitted to them, and for ``method="centroid"`` the squared-weight centroid of the bilinear
interpolant. Here it is written with NumPy over stacks of same-size windows (vectorised
over windows, no loop per target or per pixel); :mod:`fieldcal.measure.disc_kernel` is the
same procedure compiled per window, tested against this one
(``tests/measure/test_disc_engines.py``).

Windows are given by their top-left pixel ``(x0, y0)`` and size ``S``; the pixel at row
``i``, column ``j`` of a window has its centre at ``(u, v) = (x0 + j, y0 + i)`` (docs/conventions.md
section 1).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

__all__ = ["measure_windows", "hat_sums", "squared_centroid", "window_grid", "RESULT_FIELDS",
           "GROW_PX", "CLEAR_PX", "MIN_EDGE_POINTS", "MIN_BG_DN"]

GROW_PX = 2          # the centroid's support: region grown by this many pixels
CLEAR_PX = 3.0       # the fitted outline must stay this far inside the window's ring
MIN_EDGE_POINTS = 8  # a conic needs at least this many edge points
MIN_BG_DN = 1.0      # a dark figure's background below this is taken as this (ratio signal)
_BATCH_PIXELS = 1 << 20  # pixels per stacked batch of windows
_FIT_ITERATIONS = 1  # algebraic fit; re-fits with Sampson weights change nothing measurable

RESULT_FIELDS = ("noise", "contrast", "area", "truncated", "overflow", "tight", "saturated",
                 "threshold", "eu", "ev", "ea", "eb", "angle_deg", "edge_rms", "n_edge", "fit_ok",
                 "cu", "cv")
"""What a window measurement returns, each an (n,) array: background noise [DN], figure
contrast [DN], region area [px] (of its row spans), the flags ``truncated`` (the region
touches the image border), ``overflow`` (it touches the window's edge inside the image),
``tight`` (the fitted outline comes within :data:`CLEAR_PX` of the ring), ``saturated``,
the threshold [DN of signal], the conic's centre ``eu, ev`` [px], semi-axes ``ea >= eb``
[px], ``angle_deg`` of the major axis, ``edge_rms`` [px], ``n_edge`` (edge points),
``fit_ok``, and the centre ``cu, cv`` of the chosen method [px, image coordinates]."""


# --------------------------------------------------------------------------------------
# small shared pieces
# --------------------------------------------------------------------------------------
@functools.cache
def _ring(S: int):
    """The outer 1-pixel ring of an S x S window, in order round it: (i, j) indices (4S-4,)
    and the plane design (4S-4, 3) of ``bg = c0 + c1 g(j) + c2 g(i)``."""
    i = np.concatenate([np.zeros(S, int), np.arange(1, S), np.full(S - 1, S - 1), np.arange(S - 2, 0, -1)])
    j = np.concatenate([np.arange(S), np.full(S - 1, S - 1), np.arange(S - 2, -1, -1), np.zeros(S - 2, int)])
    g = window_grid(S)
    A = np.stack([np.ones(i.size), g[j], g[i]], axis=1)
    return i, j, A


@functools.cache
def window_grid(S: int) -> np.ndarray:
    """Normalised window coordinate of pixel index 0..S-1 (the background plane's variable), (S,)."""
    return (np.arange(S) - (S - 1) / 2.0) / S


@functools.cache
def hat_sums(upsample):
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
        g = window_grid(self.S)
        c = self.coef
        shape = (-1,) + (1,) * (np.ndim(i) - 1)
        return c[:, 0].reshape(shape) + c[:, 1].reshape(shape) * g[j] + c[:, 2].reshape(shape) * g[i]

    def signal(self, raw_vals, bg_vals):
        """Signal at pixels with values ``raw_vals`` where the background is ``bg_vals``."""
        raw_vals = np.asarray(raw_vals, np.float64)
        if self.sign < 0:
            c0 = self.coef[:, 0].reshape((-1,) + (1,) * (raw_vals.ndim - 1))
            return (bg_vals - raw_vals) * c0 / np.maximum(bg_vals, MIN_BG_DN)
        return raw_vals - bg_vals


# --------------------------------------------------------------------------------------
# the steps of one stack of same-size windows
# --------------------------------------------------------------------------------------
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
        coef[:, 0] = np.maximum(coef[:, 0], MIN_BG_DN)
    return _Background(coef, sign, S), noise


def _extreme_and_contrast(raw, bgd: _Background, su, sv, step):
    """The extreme signal pixel ``(sy, sx)`` in a box around the candidate and the figure's
    level ``contrast`` (3 x 3 mean of the signal there) [DN], each (n,)."""
    n, S, _ = raw.shape
    ar = np.arange(n)
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
    return sy, sx, np.maximum(contrast, 1e-6)


def _signal_stack(raw, bgd: _Background):
    """The signal (n, S, S) float32 of whole windows (the centroid method needs it)."""
    n, S, _ = raw.shape
    g = window_grid(S).astype(np.float32)
    c = bgd.coef.astype(np.float32)
    bg = c[:, 0, None, None] + c[:, 1, None, None] * g[None, None, :] + c[:, 2, None, None] * g[None, :, None]
    Y = raw.astype(np.float32)
    if bgd.sign > 0:
        Y -= bg
    else:                       # c0 (bg - raw) / bg
        np.divide(Y, np.maximum(bg, np.float32(MIN_BG_DN)), out=Y)
        np.subtract(1.0, Y, out=Y)
        Y *= c[:, 0, None, None]
    return Y


def _isodata(Y, contrast, max_iter=8):
    """The paper's iterative threshold per window (start at the mean; mean of the two class
    means; repeat until it moves by at most 1e-3 of the figure's level, at most ``max_iter``
    times), kept within [0.3, 0.7] of the figure's level. Each window stops on its own
    (its threshold does not depend on the other windows of the stack)."""
    n = Y.shape[0]
    flat = Y.reshape(n, -1)
    total = flat.sum(axis=1, dtype=np.float64)
    N = flat.shape[1]
    t = total / N
    active = np.arange(n)
    for _ in range(max_iter):
        sub = flat[active]
        above = sub > t[active, None].astype(np.float32)
        n1 = np.count_nonzero(above, axis=1)
        s1 = np.einsum("ij,ij->i", sub, above.view(np.uint8).astype(np.float32), dtype=np.float64)
        t_new = 0.5 * (s1 / np.maximum(n1, 1) + (total[active] - s1) / np.maximum(N - n1, 1))
        done = np.abs(t_new - t[active]) <= 1e-3 * contrast[active]
        t[active] = t_new
        active = active[~done]
        if not active.size:
            break
    return np.clip(t, 0.3 * contrast, 0.7 * contrast)


def _threshold_mask(raw, bgd: _Background, contrast, method, pad):
    """The threshold ``t`` (n,) [DN of signal] and the mask of pixels beyond it, written into
    a column of windows separated by ``pad`` empty rows, (n, S + pad, S) uint8; the signal
    stack ``Y`` for the centroid method (else None)."""
    n, S, _ = raw.shape
    g = window_grid(S)
    M = np.zeros((n, S + pad, S), np.uint8)
    Mv = M[:, :S, :].view(bool)
    Y = None
    if method == "centroid":
        Y = _signal_stack(raw, bgd)
        t = _isodata(Y, contrast)
        np.greater(Y, t[:, None, None].astype(np.float32), out=Mv)
        return t, M, Y
    t = 0.5 * contrast
    c = bgd.coef
    if bgd.sign < 0:       # figure where c0 (bg - raw) / bg > t: raw < bg (1 - t / c0)
        k = 1.0 - t / c[:, 0]
        T = (c[:, 0] * k)[:, None, None] + (c[:, 1] * k)[:, None, None] * g[None, None, :]
        T = T.astype(np.float32) + ((c[:, 2] * k)[:, None, None] * g[None, :, None]).astype(np.float32)
        np.less(raw, T, out=Mv)
    else:                  # figure where raw > bg + t
        T = ((c[:, 0] + t)[:, None, None] + c[:, 1, None, None] * g[None, None, :]).astype(np.float32) \
            + (c[:, 2, None, None] * g[None, :, None]).astype(np.float32)
        np.greater(raw, T, out=Mv)
    return t, M, Y


def _grow_regions(M, sy, sx):
    """Region growing: the 8-connected component of the mask holding the seed ``(sy, sx)``,
    (n, S + pad, S) bool (all windows labelled in one call; the pad rows keep them apart)."""
    n, Sp, S = M.shape
    _, labels = cv2.connectedComponents(M.reshape(n * Sp, S), connectivity=8, ltype=cv2.CV_32S)
    labels = labels.reshape(n, Sp, S)
    seed_label = labels[np.arange(n), sy, sx]
    region = labels == seed_label[:, None, None]
    region &= (seed_label > 0)[:, None, None]
    return region


def _flip_rows(mask):
    """``mask[:, :, ::-1]`` as a contiguous copy (bool (n, S, S))."""
    n, a, b = mask.shape
    return cv2.flip(mask.view(np.uint8).reshape(n * a, b), 1).reshape(n, a, b).view(bool)


@dataclass
class _Outline:
    """First and last region pixel of every row (``L``, ``Rr``) and column (``T``, ``B``),
    each (n, S), and whether the row / column holds any (``row_has``, ``col_has``)."""

    L: np.ndarray
    Rr: np.ndarray
    T: np.ndarray
    B: np.ndarray
    row_has: np.ndarray
    col_has: np.ndarray


def _outline(region) -> _Outline:
    """The region's outline scans (argmax finds the first True fast along a contiguous
    axis: the columns are scanned in a transposed copy, the last True in copies flipped by
    OpenCV)."""
    n, S, _ = region.shape
    ar = np.arange(n)
    regionT = np.ascontiguousarray(region.transpose(0, 2, 1))
    L = np.argmax(region, axis=2)                       # (n, S) over rows i
    Rr = S - 1 - np.argmax(_flip_rows(region), axis=2)
    T = np.argmax(regionT, axis=2)                      # (n, S) over columns j
    B = S - 1 - np.argmax(_flip_rows(regionT), axis=2)
    rows = np.broadcast_to(np.arange(S), (n, S))
    row_has = region[ar[:, None], rows, L]
    col_has = region[ar[:, None], T, rows]
    return _Outline(L, Rr, T, B, row_has, col_has)


def _border_flags(o: _Outline, y0, x0, S, H, W):
    """``truncated`` (the region touches the image border), ``overflow`` (it touches the
    window's edge inside the image), the window-at-border flags and the region's area."""
    touch_l, touch_r = (o.row_has & (o.L == 0)).any(axis=1), (o.row_has & (o.Rr == S - 1)).any(axis=1)
    touch_t, touch_b = (o.col_has & (o.T == 0)).any(axis=1), (o.col_has & (o.B == S - 1)).any(axis=1)
    at = (y0 == 0, y0 + S == H, x0 == 0, x0 + S == W)                   # top, bottom, left, right
    truncated = (touch_t & at[0]) | (touch_b & at[1]) | (touch_l & at[2]) | (touch_r & at[3])
    overflow = (touch_t & ~at[0]) | (touch_b & ~at[1]) | (touch_l & ~at[2]) | (touch_r & ~at[3])
    area = np.where(o.row_has, o.Rr - o.L + 1, 0).sum(axis=1).astype(float)   # of the row spans
    return truncated, overflow, at, area


def _outline_points(raw, bgd, t, o: _Outline, S):
    """Edge points (n, 4S) [window px] at level ``t`` on the outline of each region.

    For every row the first and last region pixel (left, right) and for every column the
    first and last (top, bottom): the edge lies between that pixel (signal above ``t``)
    and its outside neighbour (not above ``t``), where the linear interpolation of the
    signal crosses ``t``.
    """
    n = raw.shape[0]
    rows = np.broadcast_to(np.arange(S), (n, S))
    c = bgd.coef.astype(np.float32)
    g = window_grid(S).astype(np.float32)
    flat = raw.reshape(-1)
    base = (np.arange(n) * (S * S))[:, None]
    tt = t.astype(np.float32)[:, None]
    inv_s = np.float32(1.0 / S)
    # the four sides: (row index, column index, step to the outside pixel (di, dj))
    sides = ((rows, o.L, 0, -1), (rows, o.Rr, 0, 1), (o.T, rows, -1, 0), (o.B, rows, 1, 0))
    px, py = [], []
    for i_in, j_in, di, dj in sides:
        i_out = np.clip(i_in + di, 0, S - 1)
        j_out = np.clip(j_in + dj, 0, S - 1)
        bg_in = c[:, 0:1] + c[:, 1:2] * g[j_in] + c[:, 2:3] * g[i_in]
        bg_out = bg_in + (c[:, 1:2] * (dj * inv_s) + c[:, 2:3] * (di * inv_s))
        r_in = flat.take(base + i_in * S + j_in).astype(np.float32)
        r_out = flat.take(base + i_out * S + j_out).astype(np.float32)
        if bgd.sign < 0:          # c0 (bg - raw) / bg, see _Background
            s_in = c[:, 0:1] * (1.0 - r_in / np.maximum(bg_in, MIN_BG_DN))
            s_out = c[:, 0:1] * (1.0 - r_out / np.maximum(bg_out, MIN_BG_DN))
        else:
            s_in, s_out = r_in - bg_in, r_out - bg_out
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.clip((s_in - tt) / (s_in - s_out), 0.0, 1.0)    # from the inside pixel
        f = np.nan_to_num(f, nan=0.5).astype(np.float64)
        # the point moves from its inside pixel towards the outside one by f
        px.append(j_in + dj * f)
        py.append(i_in + di * f)
    valid = np.concatenate([o.row_has & (o.L >= 1), o.row_has & (o.Rr <= S - 2),
                            o.col_has & (o.T >= 1), o.col_has & (o.B <= S - 2)], axis=1)
    return np.concatenate(px, axis=1), np.concatenate(py, axis=1), valid


def squared_centroid(Y, support, upsample):
    """Grey centroid with squared weights of the bilinear interpolant (the module docstring of
    :mod:`fieldcal.measure.discs`, ``"centroid"``).

    Parameters
    ----------
    Y : (n, S, S) float32 ndarray
        The signal of each window [DN].
    support : (n, S, S) bool ndarray
        Pixels that take part (elsewhere the signal counts as 0).
    upsample : int or None
        The bilinear interpolation factor (None: the continuous limit).

    Returns
    -------
    u, v : (n,) ndarray
        The centre in window coordinates [px].
    """
    Wt = np.where(support, np.maximum(Y, 0.0), 0.0).astype(np.float32)
    S = Wt.shape[1]
    G0, G1 = hat_sums(upsample)
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
    ok = counts >= MIN_EDGE_POINTS
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


def _tight(fit, S, at):
    """Whether the fitted outline comes within :data:`CLEAR_PX` of the window's ring on a side
    that is not the image border (then the background took in the blur tail)."""
    at_t, at_b, at_l, at_r = at
    ca, sa = np.cos(np.radians(fit["angle_deg"])), np.sin(np.radians(fit["angle_deg"]))
    hx = np.sqrt((fit["ea"] * ca) ** 2 + (fit["eb"] * sa) ** 2) + CLEAR_PX
    hy = np.sqrt((fit["ea"] * sa) ** 2 + (fit["eb"] * ca) ** 2) + CLEAR_PX
    with np.errstate(invalid="ignore"):
        return (((fit["eu"] - hx < 1) & ~at_l) | ((fit["eu"] + hx > S - 2) & ~at_r)
                | ((fit["ev"] - hy < 1) & ~at_t) | ((fit["ev"] + hy > S - 2) & ~at_b))


def _centroid_of_regions(Y, region_padded, upsample):
    """The squared-weight centroid over the region grown by :data:`GROW_PX` (window coords).

    The dilation runs on the padded column of windows: the ``GROW_PX + 1`` empty rows
    between windows keep one window's support out of the next.
    """
    n, Sp, S = region_padded.shape
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * GROW_PX + 1,) * 2)
    support = cv2.dilate(region_padded.view(np.uint8).reshape(n * Sp, S), kernel)
    support = support.reshape(n, Sp, S)[:, :S, :].view(bool)
    return squared_centroid(Y, support, upsample)


def _measure_stack(img, y0, x0, su, sv, S, *, sign, step, method, upsample, sat_level, noise_dn):
    """Measure one stack of same-size windows. Returns a dict of (n,) arrays (RESULT_FIELDS).

    ``su, sv``: candidate position in window coordinates; ``y0, x0``: window origins.
    """
    H, W = img.shape
    raw = _gather(img, y0, x0, S)
    bgd, noise = _background(raw, sign, noise_dn)
    sy, sx, contrast = _extreme_and_contrast(raw, bgd, su, sv, step)
    pad = GROW_PX + 1
    t, M, Y = _threshold_mask(raw, bgd, contrast, method, pad)
    region_padded = _grow_regions(M, sy, sx)
    del M
    region = np.ascontiguousarray(region_padded[:, :S, :])
    o = _outline(region)
    truncated, overflow, at, area = _border_flags(o, y0, x0, S, H, W)
    px, py, valid = _outline_points(raw, bgd, t, o, S)
    fit = _fit_ellipses(px, py, valid)
    # the fitted outline must keep clear of the ring (else the background took in the blur
    # tail): a window found too tight is measured again, larger
    tight = _tight(fit, S, at)
    saturated = raw.max(axis=(1, 2)) >= sat_level
    if sign < 0:
        saturated |= raw.min(axis=(1, 2)) == 0
    out = {"noise": noise, "contrast": contrast, "area": area, "truncated": truncated,
           "overflow": overflow, "tight": tight, "saturated": saturated, "threshold": t}
    out.update(fit)
    if method == "centroid":
        cu, cv = _centroid_of_regions(Y, region_padded, upsample)
    else:
        cu, cv = fit["eu"], fit["ev"]
    out["cu"] = cu + x0
    out["cv"] = cv + y0
    return out


def measure_windows(img, y0, x0, su, sv, S, *, sign, step, method, upsample, sat_level, noise_dn):
    """Measure square windows of an image (the NumPy reference of stage 3).

    Parameters
    ----------
    img : (H, W) uint8 or uint16 ndarray
        The image [DN].
    y0, x0 : (n,) int ndarray
        Top-left pixel of each window (inside the image).
    su, sv : (n,) float ndarray
        The candidate's position in window coordinates [px].
    S : (n,) int ndarray
        Side of each window [px].
    sign : {-1, 1}
        -1 for dark figures, 1 for bright ones.
    step : int
        The candidate search's sampling step [px] (sets the box searched for the extreme).
    method : {"ellipse", "centroid"}
    upsample : int or None
        The centroid method's interpolation factor.
    sat_level : int
        Pixel value counted as saturated [DN].
    noise_dn : float
        The image's noise [DN] (clips the ring differences).

    Returns
    -------
    dict of (n,) ndarray
        :data:`RESULT_FIELDS`, in the order of the windows given.
    """
    S = np.asarray(S, int)
    n = S.size
    parts, where = [], []
    for size in np.unique(S):
        same = np.flatnonzero(S == size)
        # batches of windows small enough for the CPU caches (every stage streams them)
        per = max(16, _BATCH_PIXELS // int(size) ** 2)
        for k in range(0, same.size, per):
            idx = same[k:k + per]
            parts.append(_measure_stack(img, y0[idx], x0[idx], su[idx], sv[idx], int(size), sign=sign,
                                        step=step, method=method, upsample=upsample,
                                        sat_level=sat_level, noise_dn=noise_dn))
            where.append(idx)
    if not parts:
        return {k: np.zeros(0, bool if k in ("truncated", "overflow", "tight", "saturated", "fit_ok")
                            else float) for k in RESULT_FIELDS}
    order = np.concatenate(where)
    out = {}
    for k in RESULT_FIELDS:
        col = np.concatenate([p[k] for p in parts])
        res = np.empty(n, col.dtype)
        res[order] = col
        out[k] = res
    return out
