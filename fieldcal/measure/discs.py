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
   position and size. A component too large for a disc (a disc joined to shading, a
   shadow, clutter or, for a ringed target's dot, its ring's segments) is thresholded
   again within itself, higher, until its discs stand alone (``_split``).
2. **Windows** (per candidate). A square window around each candidate, sized from its
   coarse extent, is cut out; same-size windows are stacked and measured together
   (vectorised over windows, no loop per target or per pixel) by the NumPy reference
   (:mod:`fieldcal.measure.disc_windows`), or one window at a time by the compiled kernel
   (:mod:`fieldcal.measure.disc_kernel`, the default where Numba compiles; the two are
   held to one contract, ``tests/measure/test_disc_engines.py``). A window found too small
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
     the extreme pixel (the reference labels all windows in one call, stacked in a column;
     the kernel grows it from the extreme pixel);
   - the centre, by one of two methods:

     ``"ellipse"``: sub-pixel edge points where the threshold level crosses the pixel
     grid (linear interpolation between the outermost region pixel of every row and
     column and its outside neighbour), and a conic fitted to them (algebraic fit with
     the Euclidean-invariant constraint ``a + c = 1``); the centre of the conic. Its
     precision reaches the Cramer-Rao bound of a disc in white noise (tests); the edge
     points' RMS distance to the conic is the shape figure that rejects squares.

     ``"centroid"``: the grey centroid with squared weights of the background-removed
     signal, over the region grown by ``2`` pixels, after bilinear interpolation onto a
     grid ``upsample`` times finer (the region is grown within its own window). The
     interpolation is done in closed form: the sum over the fine grid of ``F^2 (1, x, y)``
     for a bilinear ``F`` equals a weighted sum of the five neighbour products
     ``Y_ij Y_i'j'`` (``|i-i'|, |j-j'| <= 1``) with weights ``G0^2, 2 G0 G1, 2 G1^2`` from
     the hat function sampled at ``m / upsample``, so no fine grid is ever stored.
     ``upsample=1`` is the plain pixel-level squared centroid.

   Both estimate the centre of the imaged ellipse. The image of a disc's centre differs
   from it by the perspective eccentricity (:mod:`fieldcal.field.eccentricity`), applied once a
   pose is known.

4. **Filters and quality figures**: size, roundness (minor / major), edge residual of the
   ellipse fit (squares and clutter fit badly), contrast and SNR, saturation, truncation at
   the image border; duplicates (two candidates on one blob) are merged.

The default method is the one that measured more accurately on rendered images (see
``bench/README_extract.md``): :data:`DEFAULT_METHOD`.

Pixel convention: docs/conventions.md section 1, the centre of the top-left pixel
is ``(0, 0)``; the pixel at row ``i``, column ``j`` of a window whose top-left pixel is ``(x0, y0)`` has its
centre at ``(u, v) = (x0 + j, y0 + i)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pyarrow as pa
from scipy.spatial import cKDTree

from fieldcal.errors import InputError
from fieldcal.measure import disc_kernel, disc_windows
from fieldcal.measure.imageio import check_image
from fieldcal.measure.measurements import apriori_sigma, empty_measurements, measurements_table

__all__ = [
    "METHODS", "DEFAULT_METHOD", "POLARITIES", "ENGINES", "detect_targets", "default_engine",
    "estimate_noise_dn", "coarse_step", "inside_polygons",
]

METHODS = ("ellipse", "centroid")
DEFAULT_METHOD = "ellipse"
"""Chosen by measured accuracy on rendered paper-like images (bench/README_extract.md)."""
POLARITIES = ("dark", "bright")
ENGINES = ("numba", "numpy")
"""How stage 3 is computed: the compiled kernel or the NumPy reference (same contract)."""

_MARGIN_PX = 5       # window margin beyond the coarse extent: ring + blur tail + position error
_CLASS_PX = 4        # window sizes are multiples of this (stacked batches of one size)


# --------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------
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
    arr = check_image(image)
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


def _sums(hat, idx, lab, m, base):
    """Top-hat-weighted sums of the samples ``idx`` (flat indices) of components ``lab`` (0..m-1):
    ``sum w, sum w c, sum w r, sum w^2``, then about the weighted mean ``sum w dc dc,
    sum w dr dr, sum w dc dr`` (``w = hat - base``; c column, r row); each (m,)."""
    hv = hat.ravel()[idx].astype(np.float64) - base
    r, c = np.divmod(idx, hat.shape[1])

    def total(w):
        return np.bincount(lab, weights=w, minlength=m)

    sh = total(hv)
    with np.errstate(invalid="ignore", divide="ignore"):
        sc, sr = total(hv * c), total(hv * r)
        dc, dr = c - (sc / sh)[lab], r - (sr / sh)[lab]
        return sh, sc, sr, total(hv * hv), total(hv * dc * dc), total(hv * dr * dr), total(hv * dc * dr)


def _component_sums(hat, thr, base):
    """The 8-connected components of ``hat > thr`` (OpenCV) and their sums (:func:`_sums`)."""
    binary = (hat > thr).view(np.uint8)
    n, labels = cv2.connectedComponents(binary, connectivity=8, ltype=cv2.CV_32S)
    idx = np.flatnonzero(binary)
    return _sums(hat, idx, labels.ravel()[idx] - 1, n - 1, base)


def _moments(sums, step, off):
    """Position, extent and span [px] of components from their sums (:func:`_component_sums`)."""
    sh, sc, sr, shh, scc, srr, scr = sums
    with np.errstate(invalid="ignore", divide="ignore"):
        mc, mr = sc / sh, sr / sh
        vcc, vrr, vcr = scc / sh, srr / sh, scr / sh
        peak = shh / sh
        # samples' worth of full contrast -> the area, and the diameter of a disc of that area
        d_est = 2.0 * step * np.sqrt(sh / peak / math.pi)
        # extent along the longest axis: 4 sigma (a disc's diameter; 1.15 x a bar's length)
        lam = 0.5 * (vcc + vrr) + np.sqrt(0.25 * (vcc - vrr) ** 2 + vcr**2)
        span = 4.0 * step * np.sqrt(lam)
    u, v = off + step * mc, off + step * mr
    extent = np.maximum(1.1 * d_est, span + 2.0)
    return u, v, extent, span


MAX_SPLIT_LEVELS = 8
"""How many times the candidate threshold is doubled to split a component too large for a disc."""
SPLIT_RISE = 1.5
"""A part found by splitting is a candidate when it rises well above the level it was cut at
(its hat-weighted mean height at least this times the level's height): a disc does, by its
contrast; a fragment of a line or an edge cut near its own crest does not."""


def _split(hat, thr, base, step, off, max_span_px):
    """Candidates inside the components of ``hat > thr`` too large for a disc.

    A disc whose top-hat touches shading, a shadow's edge, clutter or (the dot of a ringed
    target, e.g. PhotoModeler's coded targets) its ring's segments through a gap a little
    darker than the paper joins them in one component above the first threshold, too
    large to be kept. Where the image's noise is at the estimator's floor (a JPEG's flat
    areas: 0.3 DN) that threshold is a few DN, and many discs of a shaded sheet are lost
    so. Such components are thresholded again at twice the height above ``base``
    (``thr' = base + 2 (thr - base)``) within their own samples, and again within the parts
    still too large, up to :data:`MAX_SPLIT_LEVELS` times; every part of a disc's size
    found on the way that rises above its level (:data:`SPLIT_RISE`) is a candidate (each
    sample is in at most one; the window stage measures it and its filters decide).
    Returns ``(u, v, extent)`` [px].
    """
    max_area = 0.5 * math.pi * (max_span_px / step) ** 2      # twice the largest disc's [samples]
    binary = hat > thr
    found = []
    level = float(thr)
    top = float(hat.max())
    for k in range(MAX_SPLIT_LEVELS + 1):
        n, labels = cv2.connectedComponents(binary.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
        idx = np.flatnonzero(binary)
        lab = labels.ravel()[idx] - 1
        # a component of more than twice the largest disc's area is too large without its
        # moments (the shaded floor beside a sheet); the moments of the others
        huge = np.bincount(lab, minlength=n - 1) > max_area
        sel = ~huge[lab]
        sums = _sums(hat, idx[sel], lab[sel], n - 1, base)
        u, v, extent, span = _moments(sums, step, off)
        big = huge | ~(span <= max_span_px)
        if k:
            with np.errstate(invalid="ignore", divide="ignore"):
                height = sums[3] / sums[0]                  # hat-weighted mean height above base
            ok = ~big & np.isfinite(u) & np.isfinite(v) & (height >= SPLIT_RISE * (level - base))
            found.append((u[ok], v[ok], extent[ok]))
        level = base + 2.0 * (level - base)
        if not big.any() or level >= top:
            break
        in_big = np.concatenate([[False], big])
        binary = (hat > int(math.ceil(level))) & in_big[labels]
    if not found:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return tuple(np.concatenate(c) for c in zip(*found, strict=True))


def _coarse_candidates(img, step, max_diameter_px, threshold_dn, sign, min_contrast_dn, engine="numpy"):
    """Candidates on the image sampled every ``step`` pixels; returns them and the contrast
    floor used (``min_contrast_dn``, or 2 % of the sample's 0.5-99.5 percentile range).
    The components and their moments by OpenCV and NumPy (``engine="numpy"``) or compiled."""
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
    if engine == "numba":
        sums = tuple(disc_kernel.component_sums(hat, thr, base).T)
    else:
        sums = _component_sums(hat, thr, base)
    u, v, extent, span = _moments(sums, step, off)
    max_span = max_diameter_px + 2 * step
    keep = (span <= max_span) & np.isfinite(u) & np.isfinite(v)
    cand = _Candidates(u[keep], v[keep], extent[keep])
    if np.any(span > max_span):                 # only then: a frame of separate discs costs nothing more
        su, sv, sext = _split(hat, thr, base, step, off, max_span)
        cand = _Candidates(np.concatenate([cand.u, su]), np.concatenate([cand.v, sv]),
                           np.concatenate([cand.extent, sext]))
    return cand, min_contrast_dn


# --------------------------------------------------------------------------------------
# point in polygon (exclusion zones such as ArUco markers)
# --------------------------------------------------------------------------------------
def inside_polygons(u, v, polygons) -> np.ndarray:
    """Which points ``(u, v)`` [px] lie inside any of ``polygons`` (list of (m, 2) arrays [px]),
    by the even-odd rule; (n,) bool."""
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
# stage 2/3: windows, measured by an engine; a window too small is measured again, larger
# --------------------------------------------------------------------------------------
def default_engine() -> str:
    """``"numba"`` where the compiled kernel works (:func:`fieldcal.measure.disc_kernel.available`),
    else ``"numpy"``."""
    return "numba" if disc_kernel.available() else "numpy"


def _window_size(extent):
    need = np.asarray(extent) + 2 * _MARGIN_PX
    return (_CLASS_PX * np.ceil(need / _CLASS_PX)).astype(int)


def _measure_all(img, cand: _Candidates, *, engine, sign, step, method, upsample, sat_level,
                 max_diameter_px, min_snr, noise_dn):
    """Measure every candidate; windows too small for their blob are measured again, larger.

    Windows are measured in the order of their sizes (stable), the retried ones after the
    others; the result holds one entry per candidate (``index``) in that order.
    """
    measure = disc_kernel.measure_windows if engine == "numba" else disc_windows.measure_windows
    H, W = img.shape
    S_cap = min(H, W)
    S = np.minimum(_window_size(cand.extent), S_cap)
    u, v = cand.u.copy(), cand.v.copy()
    results = []
    todo = np.arange(len(u))
    for attempt in range(2):
        todo = todo[np.argsort(S[todo], kind="stable")]
        size = S[todo]
        y0 = np.clip(np.rint(v[todo]).astype(int) - size // 2, 0, H - size)
        x0 = np.clip(np.rint(u[todo]).astype(int) - size // 2, 0, W - size)
        r = measure(img, y0, x0, u[todo] - x0, v[todo] - y0, size, sign=sign, step=step, method=method,
                    upsample=upsample, sat_level=sat_level, noise_dn=noise_dn)
        r["index"] = todo
        bigger = np.minimum(S_cap, (_CLASS_PX * np.ceil(np.minimum(
            1.5 * size + 8, max_diameter_px + 2 * _MARGIN_PX + 2 * step) / _CLASS_PX)).astype(int))
        retry = ((r["overflow"] | r["tight"]) & (size < S_cap) & (attempt == 0)
                 & (r["contrast"] >= min_snr * r["noise"]) & (bigger > size))
        if retry.any():
            # re-centre on what was measured, where it was
            cu, cv = r["cu"][retry], r["cv"][retry]
            fin = np.isfinite(cu) & np.isfinite(cv)
            u[todo[retry][fin]], v[todo[retry][fin]] = cu[fin], cv[fin]
            S = S.copy()
            S[todo[retry]] = bigger[retry]
        results.append({k: val[~retry] for k, val in r.items()})
        todo = todo[retry]
        if not todo.size:
            break
    return {k: np.concatenate([r[k] for r in results]) for k in results[0]}


# --------------------------------------------------------------------------------------
# filters and the table
# --------------------------------------------------------------------------------------
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



def _reject_codes(r, snr, diameter, *, min_snr, min_contrast_dn, min_diameter_px, max_diameter_px,
                  min_roundness, max_edge_rms_px, psf_sigma_px, exclude):
    """The first filter each measurement fails (an index into the returned reasons; 0: none).

    Filters in order: overflow, no fit, snr, contrast, small, large, roundness, shape (the
    edge RMS), excluded (the centre in an exclusion polygon), duplicate (a second
    measurement of one blob).
    """
    major, minor = 2 * r["ea"], 2 * r["eb"]
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
        ins = inside_polygons(np.nan_to_num(r["cu"]), np.nan_to_num(r["cv"]), list(exclude))
        reject[ok & ins] = reasons.index("excluded")
        ok = reject == 0
    k = np.flatnonzero(ok)
    dup = ~_dedupe(r["cu"][k], r["cv"][k], 0.5 * diameter[k], snr[k])
    reject[k[dup]] = reasons.index("duplicate")
    return reject, reasons


def _table(r, sel, sigma, snr, diameter, *, method, image_name, reject=None, reasons=None):
    """The ``measurements`` table of the rows ``sel`` (with a ``reject`` column when given)."""
    major, minor = 2 * r["ea"], 2 * r["eb"]
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
    if reject is None:
        return measurements_table(cols, image_name)
    for k in ("u_px", "v_px", "sigma_px", "diameter_px", "contrast", "snr"):
        cols[k] = np.nan_to_num(np.asarray(cols[k], float), nan=-1.0)
    table = measurements_table(cols, image_name)
    return table.append_column("reject", pa.array(np.asarray(reasons)[reject[sel]]))


def _check_arguments(image, polarity, method, min_diameter_px, max_diameter_px, min_snr, upsample,
                     engine):
    img = check_image(image)
    _check_choice("polarity", polarity, POLARITIES)
    _check_choice("method", method, METHODS)
    if engine is not None:
        _check_choice("engine", engine, ENGINES)
    _check_positive("min_diameter_px", min_diameter_px, 1.0)
    _check_positive("max_diameter_px", max_diameter_px, 1.0)
    if max_diameter_px < min_diameter_px:
        raise InputError(f"max_diameter_px ({max_diameter_px}) is smaller than min_diameter_px "
                         f"({min_diameter_px})")
    _check_positive("min_snr", min_snr)
    if upsample is not None and not (isinstance(upsample, (int, np.integer)) and 1 <= upsample <= 64):
        raise InputError(f"upsample must be an integer in 1..64 or None, got {upsample!r}")
    if engine == "numba" and not disc_kernel.available():
        raise InputError(f"engine 'numba' is not available here: {disc_kernel.problem()}")
    return img


# --------------------------------------------------------------------------------------
# public
# --------------------------------------------------------------------------------------
def detect_targets(image, *, polarity: str = "dark", min_diameter_px: float = 8.0,
                   max_diameter_px: float = 64.0, method: str = DEFAULT_METHOD,
                   exclude=None, min_snr: float = 8.0, min_contrast: float | None = None,
                   min_roundness: float = 0.3,
                   max_edge_rms_px: float | None = None, upsample: int | None = 4,
                   saturation_level: int | None = None, psf_sigma_px: float = 0.8,
                   image_name: str = "", return_rejected: bool = False,
                   engine: str | None = None) -> pa.Table:
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
    engine : {"numba", "numpy"}, optional
        How the windows are measured: the compiled kernel or the NumPy reference; default
        :func:`default_engine`. Both give the same detections and flags and centres equal
        to ~1e-6 px (``tests/measure/test_disc_engines.py``).

    Returns
    -------
    pyarrow.Table
        Schema ``measurements`` (``schemas/measurements.arrow.json``), one row per target,
        ``kind = "disc"``; positions in the pixel convention of docs/conventions.md section 1.
    """
    img = _check_arguments(image, polarity, method, min_diameter_px, max_diameter_px, min_snr,
                           upsample, engine)
    sign = -1 if polarity == "dark" else 1
    sat_level = np.iinfo(img.dtype).max if saturation_level is None else int(saturation_level)

    noise_dn = estimate_noise_dn(img)
    step = coarse_step(min_diameter_px, psf_sigma_px)
    thr = max(0.5 * min_snr, 5.0) * noise_dn
    engine = engine or default_engine()
    cand, min_contrast_dn = _coarse_candidates(img, step, max_diameter_px, thr, sign, min_contrast, engine)
    if exclude is not None and len(cand.u):
        inside = inside_polygons(cand.u, cand.v, list(exclude))
        cand = _Candidates(cand.u[~inside], cand.v[~inside], cand.extent[~inside])
    if len(cand.u) == 0:
        return empty_measurements()
    r = _measure_all(img, cand, engine=engine, sign=sign, step=step, method=method,
                     upsample=upsample, sat_level=sat_level, max_diameter_px=max_diameter_px,
                     min_snr=min_snr, noise_dn=noise_dn)

    diameter = 2 * np.sqrt(r["ea"] * r["eb"])
    snr = r["contrast"] / r["noise"]
    sigma = apriori_sigma(snr, diameter, psf_sigma_px)
    reject, reasons = _reject_codes(
        r, snr, diameter, min_snr=min_snr, min_contrast_dn=min_contrast_dn,
        min_diameter_px=min_diameter_px, max_diameter_px=max_diameter_px, min_roundness=min_roundness,
        max_edge_rms_px=max_edge_rms_px, psf_sigma_px=psf_sigma_px, exclude=exclude)
    sel = np.flatnonzero((reject == 0) | return_rejected)
    sel = sel[np.lexsort((r["cu"][sel], np.round(r["cv"][sel] / 4.0)))] if sel.size else sel
    if return_rejected:
        return _table(r, sel, sigma, snr, diameter, method=method, image_name=image_name,
                      reject=reject, reasons=reasons)
    return _table(r, sel, sigma, snr, diameter, method=method, image_name=image_name)
