r"""Corrected (distortion-free) images for downstream photogrammetry, by ``cv2.remap``.

The output is the image an ideal pinhole camera would have taken: same size and pixel grid
as the sensor, principal distance ``f`` in pixels (``f_px = f / d`` unless asked
otherwise), principal point at the centre of the image. In OpenCV's convention (centre of
the top-left pixel at (0, 0), y down, z forward) its camera matrix is

    K_out = [[f_px, 0, (W - 1)/2], [0, f_px, (H - 1)/2], [0, 0, 1]]

and it has no distortion. For each output pixel ``(uo, vo)`` the maps hold the input pixel
that sees the same ray (docs/conventions.md sections 1-2):

    q = ((uo - cx) d', -(vo - cy) d') * f / f_px'       ideal point [mm], d' = f / f_px
    x' = distort(q)                                     measured point [mm] (Newton)
    (u, v) = mm_to_pixel(x')

computed exactly (Newton, :func:`fieldcal.model.camera.distort`) at nodes every 16 pixels and
interpolated between them by bicubic splines (SciPy's ``RectBivariateSpline``): on the
paper's 8208 x 6280 camera the interpolation error is below 1e-7 px, far under the float32
resolution of the maps (5e-4 px at u = 8000). The maps are evaluated in blocks of rows so a
50-megapixel image does not need gigabytes, and ``cv2.remap`` samples the input there.
Output pixels whose ray falls outside the input image get ``border_value``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import tifffile
from scipy.interpolate import RectBivariateSpline

from fieldcal.errors import ImageError, InputError
from fieldcal.model.camera import Camera, distort

__all__ = ["output_camera_matrix", "undistort_maps", "undistort_image", "undistort_file",
           "INTERPOLATION"]

INTERPOLATION = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR,
                 "cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4}
_BLOCK_PIXELS = 1 << 21
NODE_PX = 16
"""Spacing of the nodes where the maps are computed exactly [px]."""


def output_camera_matrix(camera: Camera, f_px: float | None = None) -> np.ndarray:
    """``K_out`` (3, 3) of the corrected image (module docstring)."""
    s = camera.sensor
    f = camera.f_mm / s.pixel_mm if f_px is None else float(f_px)
    if not (np.isfinite(f) and f > 0):
        raise InputError(f"f_px must be a positive number, got {f_px}", "undistort")
    return np.array([[f, 0.0, (s.width_px - 1) / 2], [0.0, f, (s.height_px - 1) / 2],
                     [0.0, 0.0, 1.0]])


class _Maps:
    """The remap tables, exact at nodes every ``NODE_PX`` pixels, bicubic splines between."""

    def __init__(self, camera: Camera, K: np.ndarray):
        s = camera.sensor
        u = np.r_[np.arange(0, s.width_px - 1, NODE_PX), s.width_px - 1].astype(float)
        v = np.r_[np.arange(0, s.height_px - 1, NODE_PX), s.height_px - 1].astype(float)
        uu, vv = np.meshgrid(u, v)
        scale = camera.f_mm / K[0, 0]                             # mm per output pixel
        q = np.stack([(uu - K[0, 2]) * scale, -(vv - K[1, 2]) * scale], axis=-1)
        uv = s.mm_to_pixel(distort(q, camera.params, check=False))
        self.inside = bool(np.isfinite(uv).all())
        uv = np.where(np.isfinite(uv), uv, -1e6)                  # no input pixel: border value
        k = 3 if min(len(u), len(v)) > 3 else 1
        self.su = RectBivariateSpline(v, u, uv[..., 0], kx=k, ky=k)
        self.sv = RectBivariateSpline(v, u, uv[..., 1], kx=k, ky=k)
        self.width = s.width_px

    def rows(self, v0: int, v1: int):
        v = np.arange(v0, v1, dtype=float)
        u = np.arange(self.width, dtype=float)
        return self.su(v, u).astype(np.float32), self.sv(v, u).astype(np.float32)


def undistort_maps(camera: Camera, *, f_px: float | None = None, rows: tuple[int, int] | None = None):
    """The remap tables of the corrected image (module docstring).

    Parameters
    ----------
    camera : Camera
    f_px : float, optional
        Principal distance of the output image [px]; default ``f / d``.
    rows : (v0, v1), optional
        Only these output rows (default all).

    Returns
    -------
    map_u, map_v : (v1 - v0, W) float32 ndarrays
        Input pixel coordinates [px] for each output pixel.
    K_out : (3, 3) ndarray
    """
    s = camera.sensor
    K = output_camera_matrix(camera, f_px)
    v0, v1 = rows or (0, s.height_px)
    if not (0 <= v0 < v1 <= s.height_px):
        raise InputError(f"rows must satisfy 0 <= v0 < v1 <= {s.height_px}, got {rows}", "undistort")
    maps = _Maps(camera, K)
    step = max(1, _BLOCK_PIXELS // s.width_px)
    parts = [maps.rows(a, min(a + step, v1)) for a in range(v0, v1, step)]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), K


def undistort_image(image, camera: Camera, *, f_px: float | None = None,
                    interpolation: str = "linear", border_value: float = 0.0):
    """The corrected image of ``image`` (H, W) or (H, W, C) taken with ``camera``.

    Returns
    -------
    out : ndarray
        Same shape and dtype as ``image``.
    K_out : (3, 3) ndarray
        Its camera matrix (OpenCV convention, no distortion).
    """
    img = np.asarray(image)
    s = camera.sensor
    if img.shape[:2] != (s.height_px, s.width_px):
        raise ImageError(f"image is {img.shape[1]} x {img.shape[0]} px but the calibration's "
                         f"sensor is {s.width_px} x {s.height_px} px", "undistort")
    if interpolation not in INTERPOLATION:
        raise InputError(f"interpolation must be one of {', '.join(INTERPOLATION)}, got "
                         f"{interpolation!r}", "undistort")
    K = output_camera_matrix(camera, f_px)
    out = np.empty_like(img)
    maps = _Maps(camera, K)
    step = max(1, _BLOCK_PIXELS // s.width_px)
    for a in range(0, s.height_px, step):
        b = min(a + step, s.height_px)
        mu, mv = maps.rows(a, b)
        try:
            out[a:b] = cv2.remap(img, mu, mv, INTERPOLATION[interpolation],
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)
        except cv2.error as e:
            raise ImageError(f"cv2.remap cannot resample {img.dtype} images with "
                             f"{1 if img.ndim == 2 else img.shape[2]} channel(s): "
                             f"{' '.join(str(e).split())[-120:]}", "undistort") from None
    return out, K


def undistort_file(camera: Camera, in_path, out_path, *, f_px: float | None = None,
                   interpolation: str = "linear", provenance: dict | None = None) -> dict:
    """Read a TIFF, write its corrected image as TIFF; returns the output camera as a dict.

    The output keeps the input's dtype and channels, is zlib-compressed, and carries the
    returned dict as JSON in its ImageDescription tag (``K`` in OpenCV's convention,
    ``distortion`` none, and ``provenance``).
    """
    src = Path(in_path)
    try:
        with tifffile.TiffFile(src) as tif:
            page = tif.pages.first
            photometric = page.photometric
            img = page.asarray()
    except FileNotFoundError:
        raise ImageError("file not found", str(src)) from None
    except (tifffile.TiffFileError, ValueError, OSError) as e:
        raise ImageError(f"cannot read the TIFF: {e}", str(src)) from None
    if img.ndim == 3 and img.shape[0] in (3, 4) and img.shape[-1] not in (3, 4):
        img = np.moveaxis(img, 0, -1)       # planar -> interleaved
    if img.ndim not in (2, 3):
        raise ImageError(f"expected a 2-D image (or one with channels last), got shape {img.shape}",
                         str(src))
    try:
        out, K = undistort_image(img, camera, f_px=f_px, interpolation=interpolation)
    except ImageError as e:
        raise ImageError(e.reason, str(src)) from None
    info = {"schema": "fieldcal.undistorted/1", "source": src.name,
            "width_px": int(out.shape[1]), "height_px": int(out.shape[0]),
            "K": K.tolist(), "distortion": None,
            "convention": "OpenCV: centre of the top-left pixel at (0, 0), x right, y down, "
                          "z forward", "interpolation": interpolation,
            "provenance": dict(provenance or {})}
    dst = Path(out_path)
    rgb = out.ndim == 3 and out.shape[-1] in (3, 4) and photometric == tifffile.PHOTOMETRIC.RGB
    try:
        tifffile.imwrite(dst, out, compression="zlib", description=json.dumps(info),
                         photometric="rgb" if rgb else "minisblack",
                         planarconfig="contig" if out.ndim == 3 else None)
    except OSError as e:
        raise ImageError(f"cannot write: {e}", str(dst)) from None
    return info
