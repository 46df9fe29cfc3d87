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
    img = np.asarray(image)
    if img.ndim != 2 or img.size == 0 or not (np.issubdtype(img.dtype, np.integer)
                                               or np.issubdtype(img.dtype, np.floating)):
        raise InputError(f"measure_spot: need a 2-D array of numbers, got {img.dtype} {img.shape}")
    if upsample < 1 or window_px < 2 or min_snr <= 0:
        raise InputError(f"measure_spot: upsample >= 1, window_px >= 2 and min_snr > 0 required "
                         f"(got {upsample}, {window_px}, {min_snr})")
    if saturation_dn is None:
        saturation_dn = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else np.inf
    if np.issubdtype(img.dtype, np.floating) and not np.isfinite(img).all():
        raise InputError("measure_spot: the image has NaN or infinite pixels")

    row, col = _coarse_peak(img)
    half = int(window_px)
    while True:
        r0, r1, c0, c1 = _window(img.shape, row, col, half)
        win = img[r0:r1, c0:c1].astype(float)
        # the brightest pixel after a 3x3 box average (a single hot pixel cannot win)
        smooth = cv2.blur(win.astype(np.float32), (3, 3), borderType=cv2.BORDER_REPLICATE)
        pr, pc = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
        thr = iterative_threshold(win)
        mask = (win > thr).astype(np.uint8)
        if not mask[pr, pc]:
            break
        n_lab, labels, stats, centres = cv2.connectedComponentsWithStats(mask, connectivity=8)
        lab = labels[pr, pc]
        x, y, w, h = (int(stats[lab, k]) for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                    cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        at_window_edge = ((x == 0 and c0 > 0) or (y == 0 and r0 > 0)
                          or (x + w == win.shape[1] and c1 < img.shape[1])
                          or (y + h == win.shape[0] and r1 < img.shape[0]))
        # grow while the region reaches the window's edge or fills more than half of it
        # (the threshold and the background need background pixels around the spot)
        if (at_window_edge or max(w, h) > half) and 2 * half <= max_window_px:
            half *= 2
            row, col = r0 + pr, c0 + pc
            continue
        break
    # background and noise from the whole window (the spot is a small part of it)
    bg = float(np.median(win))
    noise = float(np.sqrt(robust_sigma(win - bg) ** 2 + 1.0 / 12.0))
    if not mask[pr, pc]:
        return _missing(f"no spot: the brightest area is not above the threshold {thr:.0f} DN",
                        win.max(), bg, noise, thr)
    region = labels == lab
    peak = float(win[region].max())
    snr = (peak - bg) / noise
    n_pix = int(stats[lab, cv2.CC_STAT_AREA])
    if snr < min_snr:
        return _missing(f"no spot: peak {peak - bg:.0f} DN above background, SNR {snr:.1f} "
                        f"< {min_snr:g}", peak, bg, noise, thr, n_pix, snr)
    if n_pix < _MIN_PIXELS:
        return _missing(f"no spot: region of {n_pix} pixel(s) only (hot pixel?)",
                        peak, bg, noise, thr, n_pix, snr)

    # sub-pixel centroid on the region's bounding box, padded by one pixel
    y0, y1 = max(y - 1, 0), min(y + h + 1, win.shape[0])
    x0, x1 = max(x - 1, 0), min(x + w + 1, win.shape[1])
    patch = np.where(region[y0:y1, x0:x1], win[y0:y1, x0:x1] - thr, 0.0)
    cu, cv = _weighted_centroid(patch, upsample)
    u, v = c0 + x0 + cu, r0 + y0 + cv
    common = (float(u), float(v), peak, bg, noise, float(thr), n_pix, float(snr))

    # what makes the position untrustworthy, most serious first
    if (x == 0 and c0 == 0) or (y == 0 and r0 == 0) or (x + w == win.shape[1] and c1 == img.shape[1]) \
            or (y + h == win.shape[0] and r1 == img.shape[0]):
        return Spot(*common, "truncated", f"the spot's region touches the image border "
                                          f"(around u={u:.0f}, v={v:.0f})")
    n_sat = int(np.count_nonzero(win[region] >= saturation_dn))
    if n_sat:
        return Spot(*common, "saturated", f"{n_sat} pixel(s) at the saturation level "
                                          f"{saturation_dn:.0f} DN")
    signal = peak - thr
    others = np.arange(1, n_lab)
    others = others[(others != lab) & (stats[others, cv2.CC_STAT_AREA] >= _MIN_PIXELS)]
    if others.size:
        other_signal = np.asarray(ndimage.maximum(win, labels, others)) - thr
        k = int(np.argmax(other_signal))
        if other_signal[k] >= double_ratio * signal:
            ou, ov = centres[others[k]]
            dist = float(np.hypot(c0 + ou - u, r0 + ov - v))
            return Spot(*common, "double", f"a second spot {dist:.0f} px away, "
                                           f"{100 * other_signal[k] / signal:.0f}% as bright")
    wgt = np.square(patch)
    ii, jj = np.mgrid[0:patch.shape[0], 0:patch.shape[1]]
    du, dv = jj - (u - c0 - x0), ii - (v - r0 - y0)
    m = np.array([[np.sum(wgt * du * du), np.sum(wgt * du * dv)],
                  [np.sum(wgt * du * dv), np.sum(wgt * dv * dv)]]) / wgt.sum()
    ev = np.linalg.eigvalsh(m)
    ratio = float(np.sqrt(ev[1] / max(ev[0], 1e-12)))
    if ratio > max_elongation:
        return Spot(*common, "double", f"elongated region (axis ratio {ratio:.1f} > "
                                       f"{max_elongation:g}): two spots merged?")
    return Spot(*common, "ok", "")
