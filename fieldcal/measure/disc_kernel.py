"""The disc detector compiled with Numba: its window stage one window at a time, and the
candidate stage's components, with no temporaries of the image's or the stack's size.

The same procedure as the NumPy reference :mod:`fieldcal.measure.disc_windows` (and the
module docstring of :mod:`fieldcal.measure.discs`, steps 1 and 3), written as loops that
Numba compiles to machine code. Where the reference makes whole-window float maps and
labels every window's mask, the kernel reads the pixels it needs straight from the image:
the background ring, the box around the candidate, then one pass over the window for the
threshold mask (with its count per row and the window's extremes for the saturation
flag). The region is grown from the extreme pixel row by row when the mask is one simple
blob (each row's mask pixels one run, each run touching the one before, no other mask
pixel: then that is the 8-connected component exactly), else by a span fill; the outline
scans come with it. Edge points and the conic fit follow. The scratch arrays of one
window are reused for the next. Stage 1's connected components of the thresholded top-hat
and their weighted moments (:func:`component_sums`) are found by a union-find over runs,
adding the same terms in the same order as the reference's ``np.bincount``.

Arithmetic follows the reference step by step, in the same precision where the reference
decides a pixel (the threshold map and the edge interpolation in float32), so a window
gives the same region; the conic is fitted in float64 with sums LLVM may reassociate (the
reference sums in float32), so centres agree to ~2e-6 px, well inside the contract's
tolerance (``tests/measure/test_disc_engines.py``).

Compilation. The kernels are compiled with ``cache=True``: the machine code is written
next to this file (or, where that is read-only, to Numba's user cache folder) and loaded by
every later process instead of compiled again (compiling takes 30-60 s on the 2-core test
machine; loading ~0.25 s after Numba's own start-up, 1-6 s there depending on the load).
:func:`warm_up` compiles (or loads) them for uint8 and uint16 images; a Dask worker calls
it when it starts (``flows.worker``) so no task pays for compilation. If Numba is missing
or cannot compile on a platform, or the environment sets ``FIELDCAL_NUMBA=0`` (the
package's one switch, :mod:`fieldcal.contract.compiled`), :func:`available` says so in one
logged line (:func:`problem`) and the detector uses the NumPy reference. ``make`` fills
the cache once after installing (:mod:`fieldcal.precompile`).
"""

from __future__ import annotations

import logging
import math
import re

import numpy as np

from fieldcal.errors import one_line
from fieldcal.measure.disc_windows import (
    CLEAR_PX,
    GROW_PX,
    MIN_BG_DN,
    MIN_EDGE_POINTS,
    RESULT_FIELDS,
    hat_sums,
)

__all__ = ["available", "problem", "warm_up", "measure_windows", "component_sums"]

log = logging.getLogger(__name__)

try:
    import numba
except Exception as err:  # noqa: BLE001 - ImportError, or an llvmlite that cannot load
    numba = None
    _IMPORT_PROBLEM = f"numba cannot be imported ({one_line(err)})"
else:
    _IMPORT_PROBLEM = None

_FLOAT_FIELDS = ("noise", "contrast", "area", "threshold", "eu", "ev", "ea", "eb", "angle_deg",
                 "edge_rms", "n_edge", "cu", "cv")
_BOOL_FIELDS = ("truncated", "overflow", "tight", "saturated", "fit_ok")
assert sorted(_FLOAT_FIELDS + _BOOL_FIELDS) == sorted(RESULT_FIELDS)
(_NOISE, _CONTRAST, _AREA, _THRESHOLD, _EU, _EV, _EA, _EB, _ANGLE, _EDGE_RMS, _N_EDGE, _CU,
 _CV) = range(len(_FLOAT_FIELDS))
_TRUNCATED, _OVERFLOW, _TIGHT, _SATURATED, _FIT_OK = range(len(_BOOL_FIELDS))


def _jit(fn=None, *, fastmath=False):
    """``numba.njit`` with the project's options; the plain function without Numba.

    ``fastmath=True`` lets LLVM reassociate sums and contract multiply-adds (vectorised
    accumulation), never assume away NaN or infinity.
    """
    if fn is None:
        return lambda f: _jit(f, fastmath=fastmath)
    if numba is None:
        return fn
    flags = {"reassoc", "contract", "arcp"} if fastmath else False
    return numba.njit(cache=True, nogil=True, error_model="numpy", boundscheck=False, fastmath=flags)(fn)


# --------------------------------------------------------------------------------------
# the steps of one window (each the namesake of a step of the NumPy reference)
# --------------------------------------------------------------------------------------
@_jit
def _background(img, oy, ox, S, g, noise_dn, sign, ring, ring_i, ring_j, med):
    """Noise [DN] and background plane (c0, c1, c2) of one window from its outer ring."""
    m = 4 * S - 4
    k = 0
    for j in range(S):                                   # the ring in the reference's order
        ring[k], ring_i[k], ring_j[k] = img[oy, ox + j], 0, j
        k += 1
    for i in range(1, S):
        ring[k], ring_i[k], ring_j[k] = img[oy + i, ox + S - 1], i, S - 1
        k += 1
    for j in range(S - 2, -1, -1):
        ring[k], ring_i[k], ring_j[k] = img[oy + S - 1, ox + j], S - 1, j
        k += 1
    for i in range(S - 2, 0, -1):
        ring[k], ring_i[k], ring_j[k] = img[oy + i, ox], i, 0
        k += 1
    clip = 5.0 * math.sqrt(2.0) * noise_dn
    total, cnt = 0.0, 0
    for k in range(m - 1):
        d = abs(ring[k + 1] - ring[k])
        if d < clip:
            total += d
            cnt += 1
    noise = max(total / max(cnt, 1) * (math.sqrt(math.pi) / 2), 0.3)
    # median of the ring sampled every m // 16 pixels (insertion sort of <= 20 values)
    nm = 0
    for k in range(0, m, max(1, m // 16)):
        v = ring[k]
        p = nm
        while p > 0 and med[p - 1] > v:
            med[p] = med[p - 1]
            p -= 1
        med[p] = v
        nm += 1
    centre = med[nm // 2] if nm % 2 else 0.5 * (med[nm // 2 - 1] + med[nm // 2])
    # the plane through the ring pixels within 4 noise of the median (normal equations)
    lim = 4.0 * noise + 0.02 * abs(centre)
    n00 = n01 = n02 = n11 = n12 = n22 = r0 = r1 = r2 = 0.0
    for k in range(m):
        v = ring[k]
        if abs(v - centre) < lim:
            a1, a2 = g[ring_j[k]], g[ring_i[k]]
            n00 += 1.0
            n01 += a1
            n02 += a2
            n11 += a1 * a1
            n12 += a1 * a2
            n22 += a2 * a2
            r0 += v
            r1 += v * a1
            r2 += v * a2
    n00 += 1e-9
    n11 += 1e-9
    n22 += 1e-9
    # Cramer's rule for the symmetric 3 x 3 system
    det = (n00 * (n11 * n22 - n12 * n12) - n01 * (n01 * n22 - n12 * n02)
           + n02 * (n01 * n12 - n11 * n02))
    c0 = (r0 * (n11 * n22 - n12 * n12) - n01 * (r1 * n22 - n12 * r2) + n02 * (r1 * n12 - n11 * r2)) / det
    c1 = (n00 * (r1 * n22 - r2 * n12) - r0 * (n01 * n22 - n12 * n02) + n02 * (n01 * r2 - r1 * n02)) / det
    c2 = (n00 * (n11 * r2 - n12 * r1) - n01 * (n01 * r2 - r1 * n02) + r0 * (n01 * n12 - n11 * n02)) / det
    if sign < 0:
        c0 = max(c0, MIN_BG_DN)
    return noise, c0, c1, c2


@_jit
def _signal(raw, bg, c0, sign):
    """The figure's signal at one pixel [DN] (reference: ``_Background.signal``)."""
    if sign < 0:
        return (bg - raw) * c0 / max(bg, MIN_BG_DN)
    return raw - bg


@_jit
def _extreme_and_contrast(img, oy, ox, S, g, c0, c1, c2, sign, su, sv, step):
    """The extreme signal pixel (sy, sx) near the candidate and the 3 x 3 mean there [DN]."""
    B = min(S, 2 * (step // 2 + 1) + 1)
    by = min(max(int(np.rint(sv)) - B // 2, 0), S - B)
    bx = min(max(int(np.rint(su)) - B // 2, 0), S - B)
    best, sy, sx = -np.inf, by, bx
    for i in range(by, by + B):
        for j in range(bx, bx + B):
            val = _signal(float(img[oy + i, ox + j]), c0 + c1 * g[j] + c2 * g[i], c0, sign)
            if val > best:
                best, sy, sx = val, i, j
    pi, pj = min(max(sy - 1, 0), S - 3), min(max(sx - 1, 0), S - 3)
    total = 0.0
    for i in range(pi, pi + 3):
        for j in range(pj, pj + 3):
            total += _signal(float(img[oy + i, ox + j]), c0 + c1 * g[j] + c2 * g[i], c0, sign)
    return sy, sx, max(total / 9.0, 1e-6)


@_jit
def _signal_window(img, oy, ox, S, g32, c0, c1, c2, sign, Y):
    """The signal of the whole window in float32, as the reference's ``_signal_stack``;
    returns the window's largest and smallest pixel."""
    c0f, c1f, c2f = np.float32(c0), np.float32(c1), np.float32(c2)
    one = np.float32(MIN_BG_DN)
    hi = img[oy, ox]
    lo = img[oy, ox]
    for i in range(S):
        row = img[oy + i, ox:ox + S]
        for j in range(S):
            v = row[j]
            hi = max(hi, v)
            lo = min(lo, v)
            bg = (c0f + c1f * g32[j]) + c2f * g32[i]
            raw = np.float32(v)
            if sign > 0:
                Y[i * S + j] = raw - bg
            else:
                Y[i * S + j] = (np.float32(1.0) - raw / max(bg, one)) * c0f
    return hi, lo


@_jit
def _isodata(Y, n, contrast):
    """The iterative threshold of one window's signal, within [0.3, 0.7] of ``contrast``."""
    total = 0.0
    for p in range(n):
        total += Y[p]
    t = total / n
    for _ in range(8):
        t32 = np.float32(t)
        n1, s1 = 0, 0.0
        for p in range(n):
            if Y[p] > t32:
                n1 += 1
                s1 += Y[p]
        t_new = 0.5 * (s1 / max(n1, 1) + (total - s1) / max(n - n1, 1))
        done = abs(t_new - t) <= 1e-3 * contrast
        t = t_new
        if done:
            break
    return min(max(t, 0.3 * contrast), 0.7 * contrast)


@_jit
def _threshold_parts(S, g, c0, c1, c2, t, sign, colpart, rowpart):
    """The ellipse method's threshold map ``colpart[j] + rowpart[i]`` (float32) [DN of raw]."""
    if sign < 0:            # figure where raw < bg (1 - t / c0)
        k = 1.0 - t / c0
        for j in range(S):
            colpart[j] = np.float32(c0 * k + (c1 * k) * g[j])
        for i in range(S):
            rowpart[i] = np.float32((c2 * k) * g[i])
    else:                   # figure where raw > bg + t
        for j in range(S):
            colpart[j] = np.float32((c0 + t) + c1 * g[j])
        for i in range(S):
            rowpart[i] = np.float32(c2 * g[i])


@_jit
def _mask_ellipse(img, oy, ox, S, sign, colpart, rowpart, mask, row_count):
    """The mask of pixels beyond the ellipse method's threshold map (1: beyond, 0: not) and
    its count per row; returns the window's largest and smallest pixel (one pass)."""
    hi = img[oy, ox]
    lo = img[oy, ox]
    for i in range(S):
        row = img[oy + i, ox:ox + S]
        rp = rowpart[i]
        n = 0
        if sign < 0:
            for j in range(S):
                v = row[j]
                hi = max(hi, v)
                lo = min(lo, v)
                m = np.float32(v) < colpart[j] + rp
                mask[i * S + j] = m
                n += m
        else:
            for j in range(S):
                v = row[j]
                hi = max(hi, v)
                lo = min(lo, v)
                m = np.float32(v) > colpart[j] + rp
                mask[i * S + j] = m
                n += m
        row_count[i] = n
    return hi, lo


@_jit
def _mask_centroid(Y, S, t32, mask, row_count):
    """The mask of pixels whose signal is beyond the centroid method's threshold, and its
    count per row."""
    for i in range(S):
        n = 0
        for j in range(S):
            m = Y[i * S + j] > t32
            mask[i * S + j] = m
            n += m
        row_count[i] = n


@_jit
def _row_run(mask, base, S, a, b, n):
    """The run of the row at ``base`` that meets columns a..b when it holds all ``n`` mask
    pixels of the row, as (lo, hi); (-1, -1) when the row has no mask pixel in a..b;
    (-2, -2) when its mask pixels are not one such run. Walks only about the ends a and b."""
    if n == 0:
        return -1, -1
    if mask[base + a]:
        lo = a
        while lo > 0 and mask[base + lo - 1]:
            lo -= 1
    else:
        lo = a + 1
        while lo <= b and not mask[base + lo]:
            lo += 1
        if lo > b:
            return -1, -1
    if mask[base + b]:
        hi = b
        while hi < S - 1 and mask[base + hi + 1]:
            hi += 1
    else:
        hi = b - 1
        while not mask[base + hi]:
            hi -= 1
    # lo and hi are mask pixels and lo - 1, hi + 1 are not: [lo, hi] is one run (and the
    # row's only one) exactly when it holds the row's n mask pixels
    if hi - lo + 1 != n:
        return -2, -2
    return lo, hi


@_jit
def _grow_simple(mask, S, sy, sx, row_count, L, R, T, B):
    """Region growing when the mask is one simple blob (the usual window): every row's mask
    pixels form one run, and from the seed's row down and then up each row's run touches
    the one before it, and no other row has mask pixels. Then those runs are the seed's
    8-connected component exactly (they hold every mask pixel); returns False (nothing
    decided) otherwise."""
    for k in range(S):
        L[k], R[k], T[k], B[k] = S, -1, S, -1
    if mask[sy * S + sx] == 0:
        return False                      # empty region: the general fill says so
    lo, hi = _row_run(mask, sy * S, S, sx, sx, row_count[sy])
    if lo < 0:
        return False
    L[sy], R[sy] = lo, hi
    r0 = r1 = sy
    for d in (1, -1):
        plo, phi, i = L[sy], R[sy], sy + d
        while 0 <= i < S:
            a, b = _row_run(mask, i * S, S, max(plo - 1, 0), min(phi + 1, S - 1), row_count[i])
            if a == -2:
                return False
            if a < 0:
                break
            L[i], R[i] = a, b
            r0, r1 = min(r0, i), max(r1, i)
            plo, phi, i = a, b, i + d
    for i in range(S):                    # a mask pixel outside the rows reached: not one blob
        if (i < r0 or i > r1) and row_count[i]:
            return False
    # first and last row of every column: the union of the runs from the top (bottom) down
    # (up) to a row is one interval, each run touching the one before it
    cl, cr = L[r0], R[r0]
    for j in range(cl, cr + 1):
        T[j] = r0
    for i in range(r0 + 1, r1 + 1):
        for j in range(L[i], cl):
            T[j] = i
        for j in range(cr + 1, R[i] + 1):
            T[j] = i
        cl, cr = min(cl, L[i]), max(cr, R[i])
    cl, cr = L[r1], R[r1]
    for j in range(cl, cr + 1):
        B[j] = r1
    for i in range(r1 - 1, r0 - 1, -1):
        for j in range(L[i], cl):
            B[j] = i
        for j in range(cr + 1, R[i] + 1):
            B[j] = i
        cl, cr = min(cl, L[i]), max(cr, R[i])
    return True


@_jit
def _grow_region(mask, S, sy, sx, stack, L, R, T, B):
    """Region growing: the 8-connected component of ``mask`` that holds (sy, sx).

    A span fill (Heckbert's seed fill): a run of mask pixels along a row is marked as a
    whole (``mask`` 2), and the row beyond it in the direction of travel is searched, over
    the run widened by one pixel each side (8-connectivity), for runs not yet marked; the
    row behind is searched again only where the run overhangs the run it was found from.
    ``L, R`` receive the first and last region pixel of each row, ``T, B`` those of each
    column (scanned within the region's bounding box afterwards). ``stack`` is (S * S, 4).
    """
    for k in range(S):
        L[k], R[k], T[k], B[k] = S, -1, S, -1
    base = sy * S
    if mask[base + sx] != 1:
        return
    lo, hi = sx, sx
    while lo > 0 and mask[base + lo - 1] == 1:
        lo -= 1
    while hi < S - 1 and mask[base + hi + 1] == 1:
        hi += 1
    _mark_run(mask, S, sy, lo, hi, L, R)
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = sy + 1, lo, hi, 1
    stack[1, 0], stack[1, 1], stack[1, 2], stack[1, 3] = sy - 1, lo, hi, -1
    top = 2
    while top > 0:
        top -= 1
        i, plo, phi, d = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        if i < 0 or i >= S:
            continue
        base = i * S
        a, b = max(plo - 1, 0), min(phi + 1, S - 1)
        k = a
        while k <= b:
            if mask[base + k] != 1:
                k += 1
                continue
            lo, hi = k, k
            if k == a:                   # a run found further left is never adjacent to one
                while lo > 0 and mask[base + lo - 1] == 1:
                    lo -= 1
            while hi < S - 1 and mask[base + hi + 1] == 1:
                hi += 1
            _mark_run(mask, S, i, lo, hi, L, R)
            stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3] = i + d, lo, hi, d
            top += 1
            if lo < plo or hi > phi:     # overhangs its parent run: search the row behind too
                stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3] = i - d, lo, hi, -d
                top += 1
            k = hi + 2
    _column_ends(mask, S, L, R, T, B)


@_jit
def _mark_run(mask, S, i, lo, hi, L, R):
    """Mark pixels lo..hi of row i as region (2) and widen the row's ends L, R."""
    base = i * S
    for k in range(lo, hi + 1):
        mask[base + k] = 2
    L[i] = min(L[i], lo)
    R[i] = max(R[i], hi)


@_jit
def _column_ends(mask, S, L, R, T, B):
    """First and last region row ``T, B`` of every column, within the bounding box."""
    r0, r1, c0, c1 = S, -1, S, -1
    for i in range(S):
        if R[i] >= 0:
            r0, r1 = min(r0, i), i
            c0, c1 = min(c0, L[i]), max(c1, R[i])
    for j in range(c0, c1 + 1):
        for i in range(r0, r1 + 1):
            if mask[i * S + j] == 2:
                T[j] = i
                break
        for i in range(r1, r0 - 1, -1):
            if mask[i * S + j] == 2:
                B[j] = i
                break


@_jit
def _edge_point(img, oy, ox, S, i_in, j_in, di, dj, g32, c0f, c1f, c2f, inv_s, t32, sign):
    """Fraction of the way from an inside outline pixel to its outside neighbour where the
    signal crosses the threshold (float32 as the reference's ``_outline_points``)."""
    bg_in = (c0f + c1f * g32[j_in]) + c2f * g32[i_in]
    bg_out = bg_in + (c1f * (np.float32(dj) * inv_s) + c2f * (np.float32(di) * inv_s))
    r_in = np.float32(img[oy + i_in, ox + j_in])
    r_out = np.float32(img[oy + i_in + di, ox + j_in + dj])
    if sign < 0:
        one = np.float32(1.0)
        s_in = c0f * (one - r_in / max(bg_in, np.float32(MIN_BG_DN)))
        s_out = c0f * (one - r_out / max(bg_out, np.float32(MIN_BG_DN)))
    else:
        s_in, s_out = r_in - bg_in, r_out - bg_out
    f = (s_in - t32) / (s_in - s_out)
    if f != f:
        return 0.5
    return float(min(max(f, np.float32(0.0)), np.float32(1.0)))


@_jit
def _outline_points(img, oy, ox, S, g32, c0, c1, c2, t, sign, L, R, T, B, px, py):
    """Sub-pixel edge points [window px] on the region's outline; returns how many."""
    c0f, c1f, c2f = np.float32(c0), np.float32(c1), np.float32(c2)
    inv_s, t32 = np.float32(1.0 / S), np.float32(t)
    n = 0
    for i in range(S):                                   # left ends of the rows
        if R[i] >= 0 and L[i] >= 1:
            px[n] = L[i] - _edge_point(img, oy, ox, S, i, L[i], 0, -1, g32, c0f, c1f, c2f, inv_s, t32, sign)
            py[n] = i
            n += 1
    for i in range(S):                                   # right ends
        if R[i] >= 0 and R[i] <= S - 2:
            px[n] = R[i] + _edge_point(img, oy, ox, S, i, R[i], 0, 1, g32, c0f, c1f, c2f, inv_s, t32, sign)
            py[n] = i
            n += 1
    for j in range(S):                                   # top ends of the columns
        if B[j] >= 0 and T[j] >= 1:
            px[n] = j
            py[n] = T[j] - _edge_point(img, oy, ox, S, T[j], j, -1, 0, g32, c0f, c1f, c2f, inv_s, t32, sign)
            n += 1
    for j in range(S):                                   # bottom ends
        if B[j] >= 0 and B[j] <= S - 2:
            px[n] = j
            py[n] = B[j] + _edge_point(img, oy, ox, S, B[j], j, 1, 0, g32, c0f, c1f, c2f, inv_s, t32, sign)
            n += 1
    return n


@_jit
def _solve5(N, r):
    """Solve the 5 x 5 system ``N x = r`` in place (Gaussian elimination, partial pivoting);
    the solution is left in ``r``."""
    for k in range(5):
        piv = k
        for i in range(k + 1, 5):
            if abs(N[i, k]) > abs(N[piv, k]):
                piv = i
        if piv != k:
            for j in range(5):
                N[k, j], N[piv, j] = N[piv, j], N[k, j]
            r[k], r[piv] = r[piv], r[k]
        for i in range(k + 1, 5):
            f = N[i, k] / N[k, k]
            for j in range(k, 5):
                N[i, j] -= f * N[k, j]
            r[i] -= f * r[k]
    for k in range(4, -1, -1):
        s = r[k]
        for j in range(k + 1, 5):
            s -= N[k, j] * r[j]
        r[k] = s / N[k, k]


@_jit(fastmath=True)
def _fit_ellipse(px, py, n, N, r, out):
    """Conic through n edge points (the reference's ``_fit_ellipses``, in float64); ``N``
    (5, 5) and ``r`` (5,) are scratch. Writes eu, ev, ea, eb, angle_deg, edge_rms,
    n_edge into ``out``; returns fit_ok.
    """
    cnt = max(n, 1)
    mx = my = 0.0
    for k in range(n):
        mx += px[k]
        my += py[k]
    mx /= cnt
    my /= cnt
    ss = 0.0
    for k in range(n):
        ss += (px[k] - mx) ** 2 + (py[k] - my) ** 2
    scale = math.sqrt(ss / cnt) + 1e-12
    # normal equations of the rows (y^2 - x^2, xy, x, y, 1), rhs -x^2 (upper triangle)
    n00 = n01 = n02 = n03 = n04 = n11 = n12 = n13 = n14 = n22 = n23 = n24 = n33 = n34 = 0.0
    r0 = r1 = r2 = r3 = r4 = 0.0
    inv = 1.0 / scale
    for k in range(n):
        x, y = (px[k] - mx) * inv, (py[k] - my) * inv
        d0, d1, xx = y * y - x * x, x * y, x * x
        n00 += d0 * d0
        n01 += d0 * d1
        n02 += d0 * x
        n03 += d0 * y
        n04 += d0
        n11 += d1 * d1
        n12 += d1 * x
        n13 += d1 * y
        n14 += d1
        n22 += xx
        n23 += d1
        n24 += x
        n33 += y * y
        n34 += y
        r0 -= d0 * xx
        r1 -= d1 * xx
        r2 -= x * xx
        r3 -= y * xx
        r4 -= xx
    N[0, 0], N[0, 1], N[0, 2], N[0, 3], N[0, 4] = n00 + 1e-12, n01, n02, n03, n04
    N[1, 1], N[1, 2], N[1, 3], N[1, 4] = n11 + 1e-12, n12, n13, n14
    N[2, 2], N[2, 3], N[2, 4] = n22 + 1e-12, n23, n24
    N[3, 3], N[3, 4] = n33 + 1e-12, n34
    N[4, 4] = n + 1e-12
    r[0], r[1], r[2], r[3], r[4] = r0, r1, r2, r3, r4
    for a in range(5):
        for b in range(a):
            N[a, b] = N[b, a]
    ok = n >= MIN_EDGE_POINTS
    if not ok:
        for a in range(5):
            r[a] = 0.0
            for b in range(5):
                N[a, b] = 1.0 if a == b else 0.0
    _solve5(N, r)
    cc, bb, dd, ee, ff = r[0], r[1], r[2], r[3], r[4]
    aa = 1.0 - cc
    acc = 0.0
    for k in range(n):                    # Sampson distances
        x, y = (px[k] - mx) * inv, (py[k] - my) * inv
        gx = 2 * aa * x + bb * y + dd
        gy = bb * x + 2 * cc * y + ee
        F = (aa * x + bb * y + dd) * x + (cc * y + ee) * y + ff
        acc += F * F / max(gx * gx + gy * gy, 1e-12)
    rms = math.sqrt(acc / cnt) * scale
    det = 4 * aa * cc - bb * bb
    ok = ok and det > 1e-9
    x0 = (bb * ee - 2 * cc * dd) / det
    y0 = (bb * dd - 2 * aa * ee) / det
    F0 = aa * x0 * x0 + bb * x0 * y0 + cc * y0 * y0 + dd * x0 + ee * y0 + ff
    tr, dif = aa + cc, math.sqrt((aa - cc) ** 2 + bb * bb)
    lam1, lam2 = (tr - dif) / 2, (tr + dif) / 2
    ea = np.sqrt(-F0 / lam1) * scale
    eb = np.sqrt(-F0 / lam2) * scale
    ang = 0.5 * math.degrees(math.atan2(bb, aa - cc)) + 90.0
    ok = ok and np.isfinite(ea) and np.isfinite(eb) and lam1 > 0
    nan = np.nan
    out[_EU] = mx + x0 * scale if ok else nan
    out[_EV] = my + y0 * scale if ok else nan
    out[_EA] = ea if ok else nan
    out[_EB] = eb if ok else nan
    out[_ANGLE] = np.mod(ang, 180.0) if ok else nan
    out[_EDGE_RMS] = rms if ok else nan
    out[_N_EDGE] = n
    return ok


@_jit
def _squared_centroid(Y, mask, region, S, G0, G1, tmp):
    """The centroid method on one window: the region (``mask == region``) grown by GROW_PX, the
    signal's positive part there, and the closed-form bilinear squared-weight centroid.
    ``Y`` is overwritten with the weights. Returns (u, v) in window coordinates [px]."""
    for i in range(S):                    # horizontal dilation
        for j in range(S):
            hit = 0
            for jj in range(max(j - GROW_PX, 0), min(j + GROW_PX + 1, S)):
                if mask[i * S + jj] == region:
                    hit = 1
                    break
            tmp[i * S + j] = hit
    zero = np.float32(0.0)
    for i in range(S):                    # vertical dilation, then the weights
        for j in range(S):
            hit = False
            for ii in range(max(i - GROW_PX, 0), min(i + GROW_PX + 1, S)):
                if tmp[ii * S + j]:
                    hit = True
                    break
            Y[i * S + j] = max(Y[i * S + j], zero) if hit else zero
    w0, w1, w2 = G0 * G0, 2 * G0 * G1, 2 * G1 * G1
    s0 = su = sv = 0.0
    for i in range(S):
        for j in range(S):
            a = Y[i * S + j]
            P = float(a * a)
            s0 += w0 * P
            su += w0 * P * j
            sv += w0 * P * i
            if G1 > 0:
                if j + 1 < S:
                    P = float(a * Y[i * S + j + 1])
                    s0 += w1 * P
                    su += w1 * P * (j + 0.5)
                    sv += w1 * P * i
                if i + 1 < S:
                    P = float(a * Y[(i + 1) * S + j])
                    s0 += w1 * P
                    su += w1 * P * j
                    sv += w1 * P * (i + 0.5)
                if i + 1 < S and j + 1 < S:
                    P = float(a * Y[(i + 1) * S + j + 1]) + float(Y[i * S + j + 1] * Y[(i + 1) * S + j])
                    s0 += w2 * P
                    su += w2 * P * (j + 0.5)
                    sv += w2 * P * (i + 0.5)
    return su / s0, sv / s0


@_jit
def _tight(out, S, at_t, at_b, at_l, at_r):
    """Whether the fitted outline comes within CLEAR_PX of the ring on an inside side."""
    a = math.radians(out[_ANGLE])
    ca, sa = math.cos(a), math.sin(a)
    hx = math.sqrt((out[_EA] * ca) ** 2 + (out[_EB] * sa) ** 2) + CLEAR_PX
    hy = math.sqrt((out[_EA] * sa) ** 2 + (out[_EB] * ca) ** 2) + CLEAR_PX
    eu, ev = out[_EU], out[_EV]
    return (((eu - hx < 1) and not at_l) or ((eu + hx > S - 2) and not at_r)
            or ((ev - hy < 1) and not at_t) or ((ev + hy > S - 2) and not at_b))


@_jit
def _border_flags(L, R, T, B, S, at_t, at_b, at_l, at_r, flags, out):
    """``truncated`` and ``overflow`` into ``flags``, the area of the row spans into ``out``."""
    touch_l = touch_r = touch_t = touch_b = False
    area = 0
    for k in range(S):
        if R[k] >= 0:                                    # row k holds region pixels
            touch_l = touch_l or L[k] == 0
            touch_r = touch_r or R[k] == S - 1
            area += R[k] - L[k] + 1
        if B[k] >= 0:                                    # column k does
            touch_t = touch_t or T[k] == 0
            touch_b = touch_b or B[k] == S - 1
    flags[_TRUNCATED] = (touch_t and at_t) or (touch_b and at_b) or (touch_l and at_l) or (touch_r and at_r)
    flags[_OVERFLOW] = ((touch_t and not at_t) or (touch_b and not at_b) or (touch_l and not at_l)
                        or (touch_r and not at_r))
    out[_AREA] = area


@_jit
def _measure_all(img, y0, x0, su, sv, sizes, sign, step, centroid, G0, G1, sat_level, noise_dn,
                 out_f, out_b):
    """Measure every window (the reference's ``_measure_stack``, one window at a time)."""
    H, W = img.shape
    smax = 3
    for w in range(sizes.size):
        smax = max(smax, sizes[w])
    ring = np.empty(4 * smax)
    ring_i = np.empty(4 * smax, np.int64)
    ring_j = np.empty(4 * smax, np.int64)
    med = np.empty(4 * smax)
    g, g32 = np.empty(smax), np.empty(smax, np.float32)
    colpart, rowpart = np.empty(smax, np.float32), np.empty(smax, np.float32)
    mask, tmp = np.empty(smax * smax, np.uint8), np.empty(smax * smax, np.uint8)
    stack = np.empty((smax * smax, 4), np.int64)
    Y = np.empty(smax * smax if centroid else 1, np.float32)
    L, R = np.empty(smax, np.int64), np.empty(smax, np.int64)
    T, B = np.empty(smax, np.int64), np.empty(smax, np.int64)
    row_count = np.empty(smax, np.int64)
    px, py = np.empty(4 * smax), np.empty(4 * smax)
    N, r = np.empty((5, 5)), np.empty(5)
    for w in range(sizes.size):
        S, oy, ox = sizes[w], y0[w], x0[w]
        out, flags = out_f[w], out_b[w]
        for k in range(S):
            g[k] = (k - (S - 1) / 2.0) / S
            g32[k] = np.float32(g[k])
        noise, c0, c1, c2 = _background(img, oy, ox, S, g, noise_dn, sign, ring, ring_i, ring_j, med)
        sy, sx, contrast = _extreme_and_contrast(img, oy, ox, S, g, c0, c1, c2, sign, su[w], sv[w], step)
        if centroid:
            hi, lo = _signal_window(img, oy, ox, S, g32, c0, c1, c2, sign, Y)
            t = _isodata(Y, S * S, contrast)
            _mask_centroid(Y, S, np.float32(t), mask, row_count)
        else:
            t = 0.5 * contrast
            _threshold_parts(S, g, c0, c1, c2, t, sign, colpart, rowpart)
            hi, lo = _mask_ellipse(img, oy, ox, S, sign, colpart, rowpart, mask, row_count)
        # the region is the whole mask (value 1) when the simple growth decides it, else
        # the general fill marks it (value 2)
        whole = _grow_simple(mask, S, sy, sx, row_count, L, R, T, B)
        if not whole:
            _grow_region(mask, S, sy, sx, stack, L, R, T, B)
        at_t, at_b, at_l, at_r = oy == 0, oy + S == H, ox == 0, ox + S == W
        _border_flags(L, R, T, B, S, at_t, at_b, at_l, at_r, flags, out)
        n = _outline_points(img, oy, ox, S, g32, c0, c1, c2, t, sign, L, R, T, B, px, py)
        flags[_FIT_OK] = _fit_ellipse(px, py, n, N, r, out)
        flags[_TIGHT] = _tight(out, S, at_t, at_b, at_l, at_r)
        flags[_SATURATED] = hi >= sat_level or (sign < 0 and lo == 0)
        out[_NOISE], out[_CONTRAST], out[_THRESHOLD] = noise, contrast, t
        if centroid:
            cu, cv = _squared_centroid(Y, mask, 1 if whole else 2, S, G0, G1, tmp)
        else:
            cu, cv = out[_EU], out[_EV]
        out[_CU], out[_CV] = cu + ox, cv + oy


# --------------------------------------------------------------------------------------
# stage 1: components of the thresholded top-hat and their moments
# --------------------------------------------------------------------------------------
@_jit
def _find(parent, k):
    while parent[k] != k:
        parent[k] = parent[parent[k]]
        k = parent[k]
    return k


@_jit
def _component_sums(hat, thr, base):
    """The 8-connected components of ``hat > thr`` and their top-hat-weighted sums.

    Runs of samples along each row are joined with the runs of the row above that touch
    them (union-find); components are numbered in the order of their first sample (raster
    order). The sums over each component's samples, in raster order (as ``np.bincount``
    of the reference adds them), with ``w = hat - base``: ``sum w``, ``sum w c``,
    ``sum w r``, ``sum w^2``, then about the weighted mean ``sum w dc dc``, ``sum w dr dr``,
    ``sum w dc dr`` (c column, r row of the sample). Returns a (m, 7) array.
    """
    h, w = hat.shape
    n_runs = 0
    for r in range(h):                                    # count the runs
        inside = False
        for c in range(w):
            above = hat[r, c] > thr
            if above and not inside:
                n_runs += 1
            inside = above
    run_r = np.empty(n_runs, np.int64)
    run_a = np.empty(n_runs, np.int64)
    run_b = np.empty(n_runs, np.int64)
    parent = np.empty(n_runs, np.int64)
    k = 0
    prev0 = prev1 = 0                                     # the previous row's runs [prev0, prev1)
    for r in range(h):
        row0 = k
        q0 = prev0                                        # first run above that may touch
        c = 0
        while c < w:
            if hat[r, c] <= thr:
                c += 1
                continue
            a = c
            while c < w and hat[r, c] > thr:
                c += 1
            run_r[k], run_a[k], run_b[k], parent[k] = r, a, c - 1, k
            while q0 < prev1 and run_b[q0] < a - 1:
                q0 += 1
            q = q0
            while q < prev1 and run_a[q] <= c:            # 8-connected: [a - 1, c] overlaps
                x, y = _find(parent, k), _find(parent, q)
                if x != y:
                    parent[max(x, y)] = min(x, y)
                q += 1
            k += 1
        prev0, prev1 = row0, k
    label = np.empty(n_runs, np.int64)
    m = 0
    for q in range(n_runs):                               # roots in order of first appearance
        root = _find(parent, q)
        if root == q:
            label[q] = m
            m += 1
        else:
            label[q] = label[root]
    out = np.zeros((m, 7))
    for q in range(n_runs):
        j, r = label[q], run_r[q]
        for c in range(run_a[q], run_b[q] + 1):
            hv = float(hat[r, c]) - base
            out[j, 0] += hv
            out[j, 1] += hv * c
            out[j, 2] += hv * r
            out[j, 3] += hv * hv
    for q in range(n_runs):
        j, r = label[q], run_r[q]
        mc, mr = out[j, 1] / out[j, 0], out[j, 2] / out[j, 0]
        dr = r - mr
        for c in range(run_a[q], run_b[q] + 1):
            hv = float(hat[r, c]) - base
            dc = c - mc
            out[j, 4] += hv * dc * dc
            out[j, 5] += hv * dr * dr
            out[j, 6] += hv * dc * dr
    return out


def component_sums(hat, thr, base):
    """Stage 1's components and sums, compiled (see ``_component_sums``); (m, 7) float64."""
    return _component_sums(hat, int(thr), float(base))


# --------------------------------------------------------------------------------------
# public: availability, warm-up, the stage
# --------------------------------------------------------------------------------------
_STATE = {"checked": False, "problem": _IMPORT_PROBLEM}


def _call(img, y0, x0, su, sv, S, *, sign, step, method, upsample, sat_level, noise_dn):
    n = len(S)
    out_f = np.empty((n, len(_FLOAT_FIELDS)))
    out_b = np.zeros((n, len(_BOOL_FIELDS)), np.bool_)
    G0, G1 = hat_sums(upsample)
    _measure_all(img, np.asarray(y0, np.int64), np.asarray(x0, np.int64), np.asarray(su, np.float64),
                 np.asarray(sv, np.float64), np.asarray(S, np.int64), int(sign), int(step),
                 method == "centroid", float(G0), float(G1), int(sat_level), float(noise_dn), out_f, out_b)
    res = {k: out_f[:, i] for i, k in enumerate(_FLOAT_FIELDS)}
    res.update({k: out_b[:, i] for i, k in enumerate(_BOOL_FIELDS)})
    return {k: res[k] for k in RESULT_FIELDS}


def warm_up() -> bool:
    """Compile the kernels (or load them from Numba's cache) for uint8 and uint16 images.

    Runs each on a small made-up window, both polarities and both methods, writable and
    read-only images (each a specialisation Numba compiles and caches). Call it once
    per process before the first image (a Dask worker does, ``flows.worker``). Returns
    :func:`available`.
    """
    from fieldcal.contract import compiled

    if numba is None:
        return _fail(_IMPORT_PROBLEM)
    if _STATE["checked"]:
        return _STATE["problem"] is None
    if compiled.switched_off():
        return _fail(compiled.SWITCHED_OFF)
    yy, xx = np.mgrid[0:24, 0:24]
    disc = ((yy - 11.7) ** 2 + (xx - 12.2) ** 2) < 36.0
    try:
        for dtype, hi in ((np.uint8, 200), (np.uint16, 40000)):
            for sign in (-1, 1):
                img = np.where(disc == (sign < 0), hi // 4, hi).astype(dtype)
                component_sums(img, hi // 2, 0.0)
                # a read-only image is another specialisation (an uncompressed TIFF is
                # measured in place, as a read-only view of the file's bytes)
                frozen = img.copy()
                frozen.flags.writeable = False
                for pixels, method in ((img, "ellipse"), (img, "centroid"), (frozen, "ellipse")):
                    _call(pixels, np.zeros(1, int), np.zeros(1, int), np.array([12.2]), np.array([11.7]),
                          np.array([24]), sign=sign, step=3, method=method, upsample=4,
                          sat_level=np.iinfo(dtype).max, noise_dn=1.0)
    except Exception as err:  # noqa: BLE001 - any compiler failure: fall back to the reference
        return _fail(f"the disc kernel cannot be compiled ({type(err).__name__}: {one_line(err)[:200]})")
    _STATE.update(checked=True, problem=None)
    return True


def _fail(reason: str) -> bool:
    reason = re.sub(r"\x1b\[[0-9;]*m", "", reason)          # Numba colours its messages
    if not _STATE["checked"]:
        log.warning("fieldcal: %s; measuring discs with the NumPy reference (slower)", reason)
    _STATE.update(checked=True, problem=reason)
    return False


def available() -> bool:
    """Whether the compiled kernel can be used here (compiles it on the first call)."""
    if not _STATE["checked"]:
        return warm_up()
    return _STATE["problem"] is None


def problem() -> str | None:
    """Why the kernel cannot be used (one line), or None when it can (after :func:`available`)."""
    return _STATE["problem"]


def measure_windows(img, y0, x0, su, sv, S, *, sign, step, method, upsample, sat_level, noise_dn):
    """Measure square windows of an image with the compiled kernel.

    The same parameters and results as the reference
    :func:`fieldcal.measure.disc_windows.measure_windows`.

    Raises
    ------
    RuntimeError
        The kernel is not :func:`available` (with :func:`problem` as the message).
    """
    if not available():
        raise RuntimeError(f"the compiled disc kernel is not available: {problem()}")
    return _call(img, y0, x0, su, sv, S, sign=sign, step=step, method=method, upsample=upsample,
                 sat_level=sat_level, noise_dn=noise_dn)
