"""Reading session images (docs/conventions.md section 3, "Images") with tifffile, in one pass.

Single-channel TIFF or BigTIFF, 8- or 16-bit unsigned, striped or tiled, any codec that
tifffile decodes. Multi-channel images are converted to luminance (ITU-R BT.601 weights
of the first three channels). Anything else raises :class:`ImageError` with one line
naming the file and the reason.

The pixel array is returned in its stored unsigned dtype (no float copy of a 100 MB
image is made here); measurement code converts small windows as it needs them.

**One pass per image.** The lake's observation cache and the inputs' fingerprint are keyed
by the SHA-256 of each image file's bytes (:mod:`fieldcal.contract.fingerprint`). Hashing
the file and then decoding it would read a 100 MB file twice; :func:`read_file` reads it
once into memory and hashes those bytes as they arrive, and :func:`read_image` decodes
from them (an :class:`ImageFile` is accepted wherever a path is). An uncompressed image
is not even copied: its pixel array is a view of the bytes read. Compressed images are
decoded with :func:`decode_threads` codec threads (tifffile's ``maxworkers``; the Dask
worker sets it to its own thread count, :func:`set_decode_threads`).
"""

from __future__ import annotations

import hashlib
import io
import os
import struct
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from fieldcal.errors import ImageError, InputError

__all__ = ["ImageInfo", "ImageFile", "probe_image", "read_file", "read_stream", "read_image", "check_image",
           "stat_stamp", "set_decode_threads", "decode_threads", "LUMA_WEIGHTS", "MAX_PIXELS", "MAX_FILE_BYTES",
           "pixel_sample_digest", "pixel_digest", "SAMPLE_ROWS"]

LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114])
MAX_PIXELS = 400_000_000
"""Refuse images claiming more pixels than this (a corrupt header must not allocate it)."""
MAX_FILE_BYTES = 8 * MAX_PIXELS
"""Refuse to read a file larger than this [bytes] (4 samples of 16 bits at :data:`MAX_PIXELS`)."""
_CHUNK_BYTES = 1 << 22
"""Bytes read (and hashed while in the CPU's cache) per call."""
_SEGMENT_BYTES = 1 << 22
"""Compressed bytes tifffile reads at once before decoding them (its ``buffersize``): a
zstd frame then peaks at ~1.15 x its pixels instead of ~2.6 x (bench/README_extract.md)."""
_DECODE_THREADS = 1


def set_decode_threads(n: int) -> None:
    """Codec threads for decoding a compressed image (tifffile's ``maxworkers``), >= 1.

    A Dask worker calls it with its own thread count (``flows.worker``), as it does for
    OpenCV, so that workers sharing a machine do not oversubscribe its cores.
    """
    global _DECODE_THREADS
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise InputError(f"decode threads must be an integer >= 1, got {n!r}")
    _DECODE_THREADS = int(n)


def decode_threads() -> int:
    """The codec threads :func:`read_image` uses by default (see :func:`set_decode_threads`)."""
    return _DECODE_THREADS


def check_image(image) -> np.ndarray:
    """The pixel array a measurement accepts: 2-D, uint8 or uint16, at least 8 x 8 px.

    Raises
    ------
    InputError
        Naming what is wrong (dimensions, dtype, size).
    """
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise InputError(f"image must be a 2-D array (rows, columns), got shape {arr.shape}")
    if arr.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
        raise InputError(f"image must be uint8 or uint16, got {arr.dtype}")
    if min(arr.shape) < 8:
        raise InputError(f"image of {arr.shape[1]} x {arr.shape[0]} px is too small to measure")
    return arr


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


@dataclass(frozen=True, eq=False)
class ImageFile:
    """The bytes of one image file, read once (:func:`read_file`), and their SHA-256.

    Attributes
    ----------
    path : str
        The file it was read from.
    data : (n_bytes,) uint8 ndarray
        The file's content.
    sha256 : str
        SHA-256 of ``data``, 64 lower-case hex digits (as
        :func:`fieldcal.contract.fingerprint.sha256_file` gives for the file).
    stamp : (int, int, int, int, int) or None
        :func:`stat_stamp` of the open file before it was read, so a cache of hashes can
        tell whether the file was rewritten since (None: not a local file).
    """

    path: str
    data: np.ndarray
    sha256: str
    stamp: tuple[int, int, int, int, int] | None


def stat_stamp(st: os.stat_result) -> tuple[int, int, int, int, int]:
    """A file's identity and stamp ``(size, mtime_ns, ctime_ns, inode, device)`` from its stat:
    equal stamps mean the file was not rewritten (to the filesystem's time resolution)."""
    return (int(st.st_size), int(st.st_mtime_ns), int(st.st_ctime_ns), int(st.st_ino), int(st.st_dev))


def read_file(path) -> ImageFile:
    """Read a file once and hash its bytes on the way (see the module docstring).

    Each chunk is hashed right after it is read, while it is in the CPU's cache.

    Raises
    ------
    ImageError
        The file is missing, a directory, unreadable or larger than :data:`MAX_FILE_BYTES`.
        Its content is not checked here (:func:`read_image` does).
    """
    where = _name(path)
    try:
        with open(path, "rb", buffering=0) as f:
            st = os.fstat(f.fileno())
            image = read_stream(f, st.st_size, where)
    except FileNotFoundError:
        raise ImageError("file not found", where) from None
    except IsADirectoryError:
        raise ImageError("is a directory, not a file", where) from None
    except OSError as err:
        raise ImageError(f"cannot read the file ({_short(err)})", where) from None
    return ImageFile(image.path, image.data, image.sha256, stat_stamp(st))


def read_stream(f, size: int, where: str, chunk_bytes: int = _CHUNK_BYTES) -> ImageFile:
    """The bytes of an open binary file of ``size`` bytes, read once in chunks of
    ``chunk_bytes`` (``f.readinto``), each hashed as it arrives; ``stamp`` None.

    Used for a local file (:func:`read_file`) and for an object on a store
    (:meth:`fieldcal.session.store.SessionStore.read_image`: one ranged request per chunk).

    Raises
    ------
    ImageError
        ``size`` is larger than :data:`MAX_FILE_BYTES`.
    """
    if size > MAX_FILE_BYTES:
        raise ImageError(f"file of {size} bytes is larger than any image fieldcal reads "
                         f"({MAX_FILE_BYTES} bytes)", where)
    data = np.empty(size, np.uint8)
    view = memoryview(data)
    digest = hashlib.sha256()
    pos = 0
    while pos < size:
        n = f.readinto(view[pos:pos + chunk_bytes])
        if not n:
            break
        digest.update(view[pos:pos + n])
        pos += n
    # a file that shrank while it was read is hashed as read; decoding then finds it short
    return ImageFile(where, data[:pos], digest.hexdigest(), None)


class _MemoryFile(io.RawIOBase):
    """A read-only, seekable binary stream over a 1-D uint8 array, without copying it
    (``io.BytesIO`` copies a writable buffer).

    It holds the array by weak reference: tifffile's file handle and this stream form a
    reference cycle that only Python's cyclic collector frees, and a strong reference from
    it kept every image's 80-100 MB of bytes alive until a collection happened to run
    (a worker's memory grew with the number of frames, bench/README_flow.md). The bytes
    live as long as their :class:`ImageFile`.
    """

    def __init__(self, buffer: np.ndarray):
        super().__init__()
        self._buffer = weakref.ref(buffer)
        self._size = int(buffer.nbytes)
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size}[whence]
        self._pos = max(0, base + int(offset))
        return self._pos

    def readinto(self, buffer) -> int:
        data = self._buffer()
        if data is None:
            raise ValueError("the image bytes were released before they were decoded")
        out = memoryview(buffer).cast("B")
        n = max(0, min(len(out), self._size - self._pos))
        out[:n] = memoryview(data)[self._pos:self._pos + n]
        self._pos += n
        return n


def _name(source) -> str:
    return source.path if isinstance(source, ImageFile) else os.fspath(source)


def _open(source, where: str) -> tifffile.TiffFile:
    """A TiffFile over an :class:`ImageFile`'s bytes or a path (checked to be a non-empty file)."""
    if isinstance(source, ImageFile):
        if source.data.size == 0:
            raise ImageError("empty file (0 bytes)", where)
        return tifffile.TiffFile(_MemoryFile(source.data), name=os.path.basename(where))
    if not Path(source).is_file():
        raise ImageError("file not found", where)
    if Path(source).stat().st_size == 0:
        raise ImageError("empty file (0 bytes)", where)
    return tifffile.TiffFile(source)


def _header(tif: tifffile.TiffFile, where: str) -> ImageInfo:
    """The first page's :class:`ImageInfo`, checked against what the contract allows."""
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
    if info.dtype is None or info.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
        raise ImageError(f"unsupported sample type {info.dtype} (8- or 16-bit unsigned integers only)", where)
    if info.samples not in (1, 3, 4):
        raise ImageError(f"unsupported number of samples per pixel ({info.samples}); 1, 3 or 4", where)
    if info.width_px * info.height_px > MAX_PIXELS or info.width_px <= 0 or info.height_px <= 0:
        raise ImageError(f"implausible image size {info.width_px} x {info.height_px} in the header", where)
    if depth != 1:   # a volume (SGI ImageDepth): the pixel count above would not bound the allocation
        raise ImageError(f"a volume of {depth} planes (ImageDepth) is not a single 2-D image", where)
    return info


_HEADER_ERRORS = (tifffile.TiffFileError, ValueError, OSError, KeyError, IndexError, struct.error)


def probe_image(source) -> ImageInfo:
    """Read and check the header of the first page without decoding pixels.

    ``source`` is a path or an :class:`ImageFile`.
    """
    where = _name(source)
    try:
        with _open(source, where) as tif:
            return _header(tif, where)
    except ImageError:
        raise
    except _HEADER_ERRORS as err:
        raise ImageError(f"not a readable TIFF ({_short(err)})", where) from None


def _short(err: Exception) -> str:
    text = str(err).strip().splitlines()
    return (text[0] if text else type(err).__name__)[:160]


def _view_of_bytes(tif: tifffile.TiffFile, info: ImageInfo, data: np.ndarray) -> np.ndarray | None:
    """The pixels as a view of the file's bytes, when they are stored as they are used
    (one sample, uncompressed, contiguous, native byte order, aligned); else None."""
    page = tif.pages.first
    if info.samples != 1 or not page.is_final:
        return None
    offset, size = int(page.dataoffsets[0]), info.width_px * info.height_px * info.dtype.itemsize
    if offset % info.dtype.itemsize or offset + size > data.size:
        return None
    dtype = info.dtype.newbyteorder(tif.byteorder)
    if not dtype.isnative and dtype.itemsize > 1:
        return None
    return data[offset:offset + size].view(info.dtype).reshape(info.height_px, info.width_px)


def _decode(tif: tifffile.TiffFile, info: ImageInfo, source, maxworkers: int) -> np.ndarray:
    """The first page's pixels, 2-D, in the stored dtype (luminance of a colour image)."""
    where = info.path
    arr = _view_of_bytes(tif, info, source.data) if isinstance(source, ImageFile) else None
    if arr is not None:
        return arr
    try:
        arr = tif.pages.first.asarray(maxworkers=maxworkers, buffersize=_SEGMENT_BYTES)
    except Exception as err:  # noqa: BLE001 - any decoder failure is a bad file, reported in one line
        raise ImageError(f"cannot decode pixels ({_short(err)}); truncated or corrupt file?", where) from None
    if arr.ndim == 3:
        arr = _luminance(arr, info, (info.height_px, info.width_px), where)
    if arr.shape != (info.height_px, info.width_px):
        raise ImageError(f"decoded shape {arr.shape} does not match the header", where)
    return arr


def _luminance(arr: np.ndarray, info: ImageInfo, shape: tuple[int, int], where: str) -> np.ndarray:
    """Luminance of a colour array (``shape`` rows x columns, samples last or first), in its dtype."""
    if arr.shape[-1] in (3, 4) and arr.shape[:2] == shape:
        rgb = arr[..., :3]                       # samples last (contig)
    elif arr.shape[0] in (3, 4) and arr.shape[1:] == shape:
        rgb = np.moveaxis(arr[:3], 0, -1)        # separate planes
    else:
        raise ImageError(f"unexpected pixel array shape {arr.shape}", where)
    luma = rgb @ LUMA_WEIGHTS.astype(np.float32)
    return np.clip(np.rint(luma), 0, np.iinfo(info.dtype).max).astype(info.dtype)


def read_image(source, *, expect_size: tuple[int, int] | None = None,
               maxworkers: int | None = None) -> np.ndarray:
    """Pixels of a session image as a 2-D unsigned array (rows, columns).

    Parameters
    ----------
    source : str, path-like or ImageFile
        The TIFF file, or its bytes read by :func:`read_file` (not read again).
    expect_size : (width_px, height_px), optional
        The sensor size from the session; a different image size is an error.
    maxworkers : int, optional
        Codec threads for a compressed image; default :func:`decode_threads`.

    Returns
    -------
    (H, W) uint8 or uint16 ndarray
        For an :class:`ImageFile` of an uncompressed image, a view of its bytes.

    Raises
    ------
    ImageError
        Missing, empty, corrupt, truncated or unsupported file, or wrong size; the message
        names the file and the reason in one line.
    """
    where = _name(source)
    try:
        tif = _open(source, where)
    except ImageError:
        raise
    except _HEADER_ERRORS as err:
        raise ImageError(f"not a readable TIFF ({_short(err)})", where) from None
    with tif:
        try:
            info = _header(tif, where)
        except ImageError:
            raise
        except _HEADER_ERRORS as err:
            raise ImageError(f"not a readable TIFF ({_short(err)})", where) from None
        if expect_size is not None and (info.width_px, info.height_px) != tuple(expect_size):
            raise ImageError(
                f"image is {info.width_px} x {info.height_px} px, the session's sensor is "
                f"{expect_size[0]} x {expect_size[1]} px", where)
        return _decode(tif, info, source, decode_threads() if maxworkers is None else int(maxworkers))


# --------------------------------------------------------------------------------------
# the same photograph in another encoding
# --------------------------------------------------------------------------------------
SAMPLE_ROWS = 8
"""Rows of the band in the middle of an image that :func:`pixel_sample_digest` decodes."""


def _pixels_digest(info: ImageInfo, pixels: np.ndarray) -> str:
    a = np.ascontiguousarray(pixels)
    a = a.astype(a.dtype.newbyteorder("="), copy=False)
    h = hashlib.sha256(f"{info.width_px}x{info.height_px}:{a.shape}:{a.dtype.str}:".encode())
    h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def _middle_band(tif: tifffile.TiffFile, info: ImageInfo, where: str) -> np.ndarray:
    """Rows ``[H/2 - 4, H/2 + 4)`` of the first page, decoding only the strips or tiles they lie in."""
    r0 = max(0, info.height_px // 2 - SAMPLE_ROWS // 2)
    r1 = min(info.height_px, r0 + SAMPLE_ROWS)
    page = tif.pages.first
    if info.samples == 1 and page.is_final:            # uncompressed, contiguous: read the rows only
        row_bytes = info.width_px * info.dtype.itemsize
        fh = tif.filehandle
        fh.seek(int(page.dataoffsets[0]) + r0 * row_bytes)
        raw = fh.read((r1 - r0) * row_bytes)
        return np.frombuffer(raw, info.dtype.newbyteorder(tif.byteorder)).reshape(r1 - r0, info.width_px)
    import zarr

    with page.aszarr() as store:
        z = zarr.open_array(store=store, mode="r")
        planar = z.ndim == 3 and z.shape[1:] == (info.height_px, info.width_px)
        band = np.asarray(z[:, r0:r1] if planar else z[r0:r1])
    return _luminance(band, info, (r1 - r0, info.width_px), where) if band.ndim == 3 else band


def pixel_sample_digest(path) -> str | None:
    """SHA-256 of the image's size and a band of :data:`SAMPLE_ROWS` decoded rows in its middle.

    The same photograph in any encoding (another compression, striped or tiled, byte order,
    trailing bytes) has the same digest; photographs of a scene with noise differ there. Only
    the strips or tiles of the band are read and decoded. None for a file that is not a
    readable TIFF (measuring reports it). Equal digests are confirmed by :func:`pixel_digest`.
    """
    where = os.fspath(path)
    try:
        with tifffile.TiffFile(where) as tif:
            info = _header(tif, where)
            return _pixels_digest(info, _middle_band(tif, info, where))
    except Exception:  # noqa: BLE001 - any unreadable file: not compared here, measuring reports it
        return None


def pixel_digest(path) -> str | None:
    """SHA-256 of the image's decoded pixels as measured (:func:`read_image`: 2-D, luminance of
    a colour image) and its size; None for a file that does not read (measuring reports it)."""
    try:
        pixels = read_image(path)
        return _pixels_digest(probe_image(path), pixels)
    except (ImageError, OSError):
        return None
