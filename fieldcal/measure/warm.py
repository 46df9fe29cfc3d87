"""Warm-up of the measuring path in a process, before its first real image.

The first image a fresh process measured cost 0.3-0.6 s more than the next ones (bench
``bench/README_flow.md``): the lazy imports behind the disc finder (SciPy's spatial
module), TIFF codecs loaded on first use, OpenCV's first ArUco detection, Numba's kernels
loaded from their cache. :func:`warm_up_measuring` pays all of it at once on a small
made-up image written in memory in each TIFF layout the renderer and cameras use (tiled
zstd, tiled deflate, striped uncompressed), once per process
(:func:`flows.calibrate.warm_process`: a Dask worker process when it starts, the flow's
own process before it starts in-process workers), so that the first measuring task
measures the work, not the start.
"""

from __future__ import annotations

import hashlib
import io

import numpy as np

__all__ = ["warm_up_measuring", "WARM_UP_NAME"]

WARM_UP_NAME = "<warm-up>"
"""The made-up file name of the warm-up images (never on disk)."""

_LAYOUTS = ({"compression": "zstd", "tile": (64, 64)},
            {"compression": "adobe_deflate", "tile": (64, 64)},
            {"compression": None, "rowsperstrip": 32})


def _made_up_image(size_px: int = 128) -> np.ndarray:
    """A uint16 image with one dark disc on a noisy bright background [DN]."""
    yy, xx = np.mgrid[0:size_px, 0:size_px]
    disc = (yy - 0.5 * size_px + 0.3) ** 2 + (xx - 0.5 * size_px - 0.2) ** 2 < (0.15 * size_px) ** 2
    noise = np.random.default_rng(0).integers(0, 64, (size_px, size_px))
    return (np.where(disc, 6000, 40000) + noise).astype(np.uint16)


def warm_up_measuring(dictionary: str | None = None) -> bool:
    """Import, load and run once everything :func:`fieldcal.measure.targets.measure_image` uses.

    Parameters
    ----------
    dictionary : str, optional
        ArUco dictionary to detect with (default: the contract's default).

    Returns
    -------
    bool
        Whether the compiled disc kernel is available
        (:func:`fieldcal.measure.disc_kernel.warm_up`; when it is not, the NumPy reference
        measures and a one-line warning says why).
    """
    import tifffile

    from fieldcal.measure import coded, disc_kernel, targets
    from fieldcal.measure.imageio import ImageFile

    ok = disc_kernel.warm_up()
    pixels = _made_up_image()
    for layout in _LAYOUTS:
        buf = io.BytesIO()
        tifffile.imwrite(buf, pixels, photometric="minisblack", metadata=None, **layout)
        data = np.frombuffer(buf.getvalue(), np.uint8)
        source = ImageFile(WARM_UP_NAME, data, hashlib.sha256(data).hexdigest(), (0, 0, 0, 0, 0))
        targets.measure_image(source, coded={"type": "aruco",
                                             "dictionary": dictionary or coded.DEFAULT_DICTIONARY},
                              name=WARM_UP_NAME)
    return ok
