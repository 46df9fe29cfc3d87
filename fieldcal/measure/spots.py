"""Sub-pixel centroid of a collimator spot (METHODS.md part B, "Spot centroid", section 1.2.1).

The goniometer photographs one bright point target per frame. Its position follows the
paper's four steps, of which this module does the first three on one frame (the fourth,
the mean of the repeated frames at an angle, is in :mod:`fieldcal.goniometer.method`):

1. **Threshold** ``T`` by the iterative (isodata, Ridler & Calvard 1978) method: start at
   the mean grey level, split the pixels into those above and at-or-below ``T``, set ``T``
   to the mean of the two class means, repeat until it stops changing.
2. **Region growing** from the brightest pixel over 8-connected pixels above ``T``
   (the connected component of ``I > T`` that holds the brightest pixel; OpenCV labels it).
3. **Sub-pixel centroid**: the region's pixel values ``I - T`` (zero outside the region)
   are interpolated bilinearly onto a grid ``upsample`` times finer, and the centroid is
   weighted by the *square* of the interpolated values, so bright pixels count more:
   ``u = sum(w u) / sum(w)`` with ``w = max(I_interp - T, 0)^2``. Subtracting ``T`` makes
   the weight fall continuously to zero at the region's edge, so the discrete boundary of
   the region does not pull the centroid.

Only a window around the brightest spot is processed, so a 40-megapixel frame costs a
block-average (to find the spot, robust to single hot pixels) plus work on a few hundred
pixels. Coordinates follow docs/conventions.md section 1: ``u`` column, ``v`` row, centre of the
top-left pixel at ``(0, 0)``.

A frame that cannot give a trustworthy position is not an error: :func:`measure_spot`
returns a :class:`Spot` whose ``flag`` says why (:data:`FLAGS`) with a one-line reason.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scipy import ndimage

from fieldcal.errors import InputError
from fieldcal.robust import robust_sigma

__all__ = ["FLAGS", "Spot", "iterative_threshold", "measure_spot"]

FLAGS: tuple[str, ...] = ("ok", "missing", "saturated", "truncated", "double")
"""What a spot measurement can be: ``ok``, or why it is left out of the calibration:
``missing`` (no spot above the noise), ``saturated`` (clipped pixels), ``truncated``
(the spot's region touches the image border), ``double`` (a second spot, or two merged)."""

_DECIMATE = 4          # block size of the coarse search for the brightest spot [px]
_MIN_PIXELS = 3        # a region smaller than this is noise or a hot pixel


@dataclass(frozen=True)
class Spot:
    """One spot measurement. Positions are NaN when ``flag == "missing"``.

    Attributes
    ----------
    u_px, v_px : float
        Centroid [px] (column, row; docs/conventions.md section 1). Also given for ``saturated``,
        ``truncated`` and ``double`` spots, for the record; do not use them.
    peak_dn : float
        Brightest pixel of the region [DN].
    background_dn, noise_dn : float
        Median and robust standard deviation (1.4826 MAD, plus quantisation) of the
        window's pixels [DN] (the spot is a small part of the window).
    threshold_dn : float
        The iterative threshold ``T`` [DN].
    n_pixels : int
        Pixels in the region grown from the brightest pixel.
    snr : float
        ``(peak - background) / noise``.
    flag : str
        One of :data:`FLAGS`.
    reason : str
        Empty when ``ok``; otherwise one line saying what was found.
    """

    u_px: float
    v_px: float
    peak_dn: float
    background_dn: float
    noise_dn: float
    threshold_dn: float
    n_pixels: int
    snr: float
    flag: str
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.flag == "ok"

    def to_dict(self) -> dict:
        return asdict(self)


def iterative_threshold(values, *, tol_dn: float = 0.5, max_iter: int = 100) -> float:
    """The isodata threshold of a set of grey values (step 1 of the module docstring).

    Parameters
    ----------
    values : array_like
        Grey values [DN], any shape.
    tol_dn : float
        Stop when the threshold moves by less than this [DN].
    max_iter : int
        Iteration limit (the iteration converges in a handful of steps on spot images).

    Returns
    -------
    float
        ``T`` [DN]; pixels ``> T`` are the bright class. For constant input, that value.
    """
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 0:
        raise InputError("iterative_threshold: no values")
    t = float(v.mean())
    for _ in range(max_iter):
        above = v > t
        if above.all() or not above.any():
            return t
        new = 0.5 * (v[above].mean() + v[~above].mean())
        if abs(new - t) < tol_dn:
            return float(new)
        t = float(new)
    return t


def _coarse_peak(image: np.ndarray) -> tuple[int, int]:
    """(row, col) of the brightest ``_DECIMATE``-pixel block's centre (hot pixels average out)."""
    h, w = image.shape
    if h < 4 * _DECIMATE or w < 4 * _DECIMATE:
        v, u = np.unravel_index(int(np.argmax(image)), image.shape)
        return int(v), int(u)
    small = cv2.resize(image, (w // _DECIMATE, h // _DECIMATE), interpolation=cv2.INTER_AREA)
    _, _, _, (bu, bv) = cv2.minMaxLoc(small)
    sy, sx = h / small.shape[0], w / small.shape[1]
    return int((bv + 0.5) * sy), int((bu + 0.5) * sx)


def _window(shape, row: int, col: int, half: int):
    h, w = shape
    r0, r1 = max(row - half, 0), min(row + half + 1, h)
    c0, c1 = max(col - half, 0), min(col + half + 1, w)
    return r0, r1, c0, c1


def _missing(reason, peak=np.nan, bg=np.nan, noise=np.nan, thr=np.nan, n=0, snr=np.nan) -> Spot:
    return Spot(np.nan, np.nan, float(peak), float(bg), float(noise), float(thr), int(n),
                float(snr), "missing", reason)


def _weighted_centroid(patch: np.ndarray, upsample: int) -> tuple[float, float]:
    """Squared-weight centroid (col, row) of ``patch`` (values ``I - T``, zero outside the
    region) after bilinear interpolation ``upsample`` times finer; coordinates in the
    patch's pixel frame (centre of its first pixel at 0)."""
    h, w = patch.shape
    if upsample > 1:
        fine = cv2.resize(patch.astype(np.float32), (w * upsample, h * upsample),
                          interpolation=cv2.INTER_LINEAR).astype(float)
        # OpenCV's pixel-centre convention: fine index j samples source coordinate (j + 0.5)/s - 0.5
        cu = (np.arange(w * upsample) + 0.5) / upsample - 0.5
        cv = (np.arange(h * upsample) + 0.5) / upsample - 0.5
    else:
        fine, cu, cv = patch.astype(float), np.arange(w, dtype=float), np.arange(h, dtype=float)
    wgt = np.square(np.maximum(fine, 0.0))
    total = wgt.sum()
    return float(wgt.sum(axis=0) @ cu / total), float(wgt.sum(axis=1) @ cv / total)


def measure_spot(image, *, window_px: int = 24, upsample: int = 4, min_snr: float = 10.0,
                 saturation_dn: float | None = None, double_ratio: float = 0.25,
                 max_elongation: float = 2.5, max_window_px: int = 256) -> Spot:
    """Find and measure the brightest spot of a frame (the module docstring's steps 1-3).

    Parameters
    ----------
    image : (H, W) ndarray
        The frame, unsigned integers (as :func:`fieldcal.measure.imageio.read_image` returns) or
        floats [DN].
    window_px : int
        Half-size of the square window around the brightest spot in which the threshold,
        the region and the centroid are computed [px]; doubled (up to ``max_window_px``)
        while the region reaches the window's edge or is wider than half the window.
    upsample : int
        Factor of the bilinear interpolation before the centroid (1: none).
    min_snr : float
        A peak less than this many noise sigmas above the background is ``missing``.
    saturation_dn : float, optional
        Pixel value at which the sensor clips [DN]; default the integer type's maximum
        (for float images: no saturation test).
    double_ratio : float
        Another region in the window whose peak signal is at least this fraction of the
        spot's makes the frame ``double``.
    max_elongation : float
        A region whose weighted second moments have an axis ratio above this is ``double``
        (two spots merged); a single spot, even oblique, is much rounder.

    Returns
    -------
    Spot
        Never raises for what the image contains; see :data:`FLAGS`.

    Raises
    ------
    InputError
        ``image`` is not a 2-D array of numbers, or an option is out of range.
    """
    img = _check_frame(image, window_px, upsample, min_snr)
    if saturation_dn is None:
        saturation_dn = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else np.inf
    w = _grow_window(img, int(window_px), max_window_px)
    # background and noise from the whole window (the spot is a small part of it)
    bg = float(np.median(w.win))
    noise = float(np.sqrt(robust_sigma(w.win - bg) ** 2 + 1.0 / 12.0))
    if not w.mask[w.pr, w.pc]:
        return _missing(f"no spot: the brightest area is not above the threshold {w.thr:.0f} DN",
                        w.win.max(), bg, noise, w.thr)
    region = w.labels == w.lab
    peak = float(w.win[region].max())
    snr = (peak - bg) / noise
    n_pix = int(w.stats[w.lab, cv2.CC_STAT_AREA])
    if snr < min_snr:
        return _missing(f"no spot: peak {peak - bg:.0f} DN above background, SNR {snr:.1f} "
                        f"< {min_snr:g}", peak, bg, noise, w.thr, n_pix, snr)
    if n_pix < _MIN_PIXELS:
        return _missing(f"no spot: region of {n_pix} pixel(s) only (hot pixel?)",
                        peak, bg, noise, w.thr, n_pix, snr)

    # sub-pixel centroid on the region's bounding box, padded by one pixel
    x, y, bw, bh = w.box
    y0, y1 = max(y - 1, 0), min(y + bh + 1, w.win.shape[0])
    x0, x1 = max(x - 1, 0), min(x + bw + 1, w.win.shape[1])
    patch = np.where(region[y0:y1, x0:x1], w.win[y0:y1, x0:x1] - w.thr, 0.0)
    cu, cv = _weighted_centroid(patch, upsample)
    u, v = w.c0 + x0 + cu, w.r0 + y0 + cv
    common = (float(u), float(v), peak, bg, noise, float(w.thr), n_pix, float(snr))
    flag, reason = _verdict(img, w, region, patch, (u, v), (x0, y0), peak, saturation_dn=saturation_dn,
                            double_ratio=double_ratio, max_elongation=max_elongation)
    return Spot(*common, flag, reason)


def _check_frame(image, window_px, upsample, min_snr) -> np.ndarray:
    """The frame as an array, checked (2-D numbers, finite) with the options."""
    img = np.asarray(image)
    if img.ndim != 2 or img.size == 0 or not (np.issubdtype(img.dtype, np.integer)
                                               or np.issubdtype(img.dtype, np.floating)):
        raise InputError(f"measure_spot: need a 2-D array of numbers, got {img.dtype} {img.shape}")
    if upsample < 1 or window_px < 2 or min_snr <= 0:
        raise InputError(f"measure_spot: upsample >= 1, window_px >= 2 and min_snr > 0 required "
                         f"(got {upsample}, {window_px}, {min_snr})")
    if np.issubdtype(img.dtype, np.floating) and not np.isfinite(img).all():
        raise InputError("measure_spot: the image has NaN or infinite pixels")
    return img


@dataclass
class _Window:
    """The window around the spot and its threshold, mask and labelled regions."""

    r0: int          # window bounds in the frame [px]
    r1: int
    c0: int
    c1: int
    win: np.ndarray  # the window's pixels, float
    pr: int          # the brightest (3 x 3 averaged) pixel, window coordinates
    pc: int
    thr: float       # the iterative threshold [DN]
    mask: np.ndarray
    n_lab: int = 0
    labels: np.ndarray | None = None
    stats: np.ndarray | None = None
    centres: np.ndarray | None = None
    lab: int = 0     # the label of the region holding (pr, pc)
    box: tuple = (0, 0, 0, 0)   # the region's bounding box (x, y, width, height) in the window


def _grow_window(img, half: int, max_window_px: int) -> _Window:
    """Steps 1-2 in a window around the coarse peak: threshold, region growing; the window's
    half-size doubles (up to ``max_window_px``) while the region reaches its edge or is
    wider than half of it (the threshold and the background need background around the spot)."""
    row, col = _coarse_peak(img)
    while True:
        r0, r1, c0, c1 = _window(img.shape, row, col, half)
        win = img[r0:r1, c0:c1].astype(float)
        # the brightest pixel after a 3x3 box average (a single hot pixel cannot win)
        smooth = cv2.blur(win.astype(np.float32), (3, 3), borderType=cv2.BORDER_REPLICATE)
        pr, pc = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
        thr = iterative_threshold(win)
        mask = (win > thr).astype(np.uint8)
        w = _Window(r0, r1, c0, c1, win, int(pr), int(pc), thr, mask)
        if not mask[pr, pc]:
            return w
        w.n_lab, w.labels, w.stats, w.centres = cv2.connectedComponentsWithStats(mask, connectivity=8)
        w.lab = int(w.labels[pr, pc])
        x, y, bw, bh = (int(w.stats[w.lab, k]) for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                          cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        w.box = (x, y, bw, bh)
        at_window_edge = ((x == 0 and c0 > 0) or (y == 0 and r0 > 0)
                          or (x + bw == win.shape[1] and c1 < img.shape[1])
                          or (y + bh == win.shape[0] and r1 < img.shape[0]))
        if (at_window_edge or max(bw, bh) > half) and 2 * half <= max_window_px:
            half *= 2
            row, col = r0 + pr, c0 + pc
            continue
        return w


def _verdict(img, w: _Window, region, patch, uv, patch_origin, peak, *, saturation_dn, double_ratio,
             max_elongation) -> tuple[str, str]:
    """What makes the position untrustworthy, most serious first: ``(flag, reason)``."""
    u, v = uv
    x, y, bw, bh = w.box
    if (x == 0 and w.c0 == 0) or (y == 0 and w.r0 == 0) or (x + bw == w.win.shape[1] and w.c1 == img.shape[1]) \
            or (y + bh == w.win.shape[0] and w.r1 == img.shape[0]):
        return "truncated", f"the spot's region touches the image border (around u={u:.0f}, v={v:.0f})"
    n_sat = int(np.count_nonzero(w.win[region] >= saturation_dn))
    if n_sat:
        return "saturated", f"{n_sat} pixel(s) at the saturation level {saturation_dn:.0f} DN"
    signal = peak - w.thr
    others = np.arange(1, w.n_lab)
    others = others[(others != w.lab) & (w.stats[others, cv2.CC_STAT_AREA] >= _MIN_PIXELS)]
    if others.size:
        other_signal = np.asarray(ndimage.maximum(w.win, w.labels, others)) - w.thr
        k = int(np.argmax(other_signal))
        if other_signal[k] >= double_ratio * signal:
            ou, ov = w.centres[others[k]]
            dist = float(np.hypot(w.c0 + ou - u, w.r0 + ov - v))
            return "double", (f"a second spot {dist:.0f} px away, "
                              f"{100 * other_signal[k] / signal:.0f}% as bright")
    ratio = _axis_ratio(patch, u - w.c0 - patch_origin[0], v - w.r0 - patch_origin[1])
    if ratio > max_elongation:
        return "double", f"elongated region (axis ratio {ratio:.1f} > {max_elongation:g}): two spots merged?"
    return "ok", ""


def _axis_ratio(patch, cu, cv) -> float:
    """Major / minor axis of the squared-weight second moments of ``patch`` about (cu, cv)."""
    wgt = np.square(patch)
    ii, jj = np.mgrid[0:patch.shape[0], 0:patch.shape[1]]
    du, dv = jj - cu, ii - cv
    m = np.array([[np.sum(wgt * du * du), np.sum(wgt * du * dv)],
                  [np.sum(wgt * du * dv), np.sum(wgt * dv * dv)]]) / wgt.sum()
    ev = np.linalg.eigvalsh(m)
    return float(np.sqrt(ev[1] / max(ev[0], 1e-12)))
