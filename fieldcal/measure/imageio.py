"""Reading session images (docs/conventions.md section 3, "Images") with tifffile.

Single-channel TIFF or BigTIFF, 8- or 16-bit unsigned, striped or tiled, any codec that
tifffile decodes. Multi-channel images are converted to luminance (ITU-R BT.601 weights
of the first three channels). Anything else raises :class:`ImageError` with one line
naming the file and the reason.

The pixel array is returned in its stored unsigned dtype (no float copy of a 100 MB
image is made here); measurement code converts small windows as it needs them.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from fieldcal.errors import ImageError

__all__ = ["ImageInfo", "probe_image", "read_image", "LUMA_WEIGHTS"]

LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114])
MAX_PIXELS = 400_000_000
"""Refuse images claiming more pixels than this (a corrupt header must not allocate it)."""


@dataclass(frozen=True)
class ImageInfo:
    """What a TIFF header says: size, samples per pixel, sample dtype, tiling, compression."""

    path: str
    width_px: int
    height_px: int
    samples: int
    dtype: np.dtype
    tiled: bool
    compression: str
    bigtiff: bool


def _name(path) -> str:
    return os.fspath(path)


def probe_image(path) -> ImageInfo:
    """Read and check the header of the first page without decoding pixels."""
    where = _name(path)
    if not Path(path).is_file():
        raise ImageError("file not found", where)
    if Path(path).stat().st_size == 0:
        raise ImageError("empty file (0 bytes)", where)
    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.pages:
                raise ImageError("TIFF has no image pages", where)
            page = tif.pages.first
            depth = int(getattr(page, "imagedepth", 1) or 1)
            dtype = np.dtype(page.dtype) if page.dtype is not None else None
            info = ImageInfo(
                path=where, width_px=int(page.imagewidth), height_px=int(page.imagelength),
                samples=int(page.samplesperpixel), dtype=dtype, tiled=bool(page.is_tiled),
                compression=str(page.compression.name) if hasattr(page.compression, "name") else str(page.compression),
                bigtiff=bool(tif.is_bigtiff))
    except ImageError:
        raise
    except (tifffile.TiffFileError, ValueError, OSError, KeyError, IndexError, struct.error) as err:
        raise ImageError(f"not a readable TIFF ({_short(err)})", where) from None
    if info.dtype is None or info.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
        raise ImageError(f"unsupported sample type {info.dtype} (8- or 16-bit unsigned integers only)", where)
    if info.samples not in (1, 3, 4):
        raise ImageError(f"unsupported number of samples per pixel ({info.samples}); 1, 3 or 4", where)
    if info.width_px * info.height_px > MAX_PIXELS or info.width_px <= 0 or info.height_px <= 0:
        raise ImageError(f"implausible image size {info.width_px} x {info.height_px} in the header", where)
    if depth != 1:   # a volume (SGI ImageDepth): the pixel count above would not bound the allocation
        raise ImageError(f"a volume of {depth} planes (ImageDepth) is not a single 2-D image", where)
    return info


def _short(err: Exception) -> str:
    text = str(err).strip().splitlines()
    return (text[0] if text else type(err).__name__)[:160]


def read_image(path, *, expect_size: tuple[int, int] | None = None) -> np.ndarray:
    """Pixels of a session image as a 2-D unsigned array (rows, columns).

    Parameters
    ----------
    path : str or path-like
        The TIFF file.
    expect_size : (width_px, height_px), optional
        The sensor size from the session; a different image size is an error.

    Raises
    ------
    ImageError
        Missing, empty, corrupt, truncated or unsupported file, or wrong size; the message
        names the file and the reason in one line.
    """
    info = probe_image(path)
    where = info.path
    if expect_size is not None and (info.width_px, info.height_px) != tuple(expect_size):
        raise ImageError(
            f"image is {info.width_px} x {info.height_px} px, the session's sensor is "
            f"{expect_size[0]} x {expect_size[1]} px", where)
    try:
        arr = tifffile.imread(path, key=0, maxworkers=1)
    except Exception as err:  # noqa: BLE001 - any decoder failure is a bad file, reported in one line
        raise ImageError(f"cannot decode pixels ({_short(err)}); truncated or corrupt file?", where) from None
    if arr.ndim == 3:
        # samples last (contig) or first (separate planes)
        if arr.shape[-1] in (3, 4) and arr.shape[:2] == (info.height_px, info.width_px):
            rgb = arr[..., :3]
        elif arr.shape[0] in (3, 4):
            rgb = np.moveaxis(arr[:3], 0, -1)
        else:
            raise ImageError(f"unexpected pixel array shape {arr.shape}", where)
        luma = rgb @ LUMA_WEIGHTS.astype(np.float32)
        arr = np.clip(np.rint(luma), 0, np.iinfo(info.dtype).max).astype(info.dtype)
    if arr.shape != (info.height_px, info.width_px):
        raise ImageError(f"decoded shape {arr.shape} does not match the header", where)
    return arr
