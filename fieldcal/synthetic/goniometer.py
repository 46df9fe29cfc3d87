"""Synthetic goniometer sessions with exact truth (METHODS.md part B, docs/conventions.md section 3).

A session is rendered the way the laboratory takes it: a collimated point target on an arm
that turns about an axis through the camera's entrance pupil, first sweeping the image of
the point along the sensor's centre row (``x`` sweep), then, with the camera turned 90 deg,
along the centre column (``y`` sweep); several frames at every encoder angle.

Geometry (docs/conventions.md sections 1-2)
--------------------------------
Everything is in the camera frame (x right, y up, looking along -z). For a sweep:

- ``r0``: the direction that the arm's encoder zero points at. The set-up is aligned so it
  lands on the sensor centre, up to a small error ``zero_px`` (the pixel it lands on minus
  the centre); ``r0`` is the true camera's ray through that pixel. A component of the
  error along the sweep is the same thing as an offset W0 of the encoder angle.
- ``a``: the arm's rotation axis. Nominally the camera's y axis (``x`` sweep) or x axis
  (``y`` sweep), made perpendicular to ``r0``; then turned about ``r0`` by ``tilt`` (the
  spot's track is inclined on the sensor) and towards ``r0`` by ``cone`` (the collimator
  is not perpendicular to the arm's axis: the track is a small circle that bows off the
  centre row).
- The target direction at encoder angle W is ``d(W) = Rot(a, -W) r0`` (``x`` sweep) or
  ``Rot(a, +W) r0`` (``y`` sweep), so that a positive angle moves the image towards +x
  (+y) as frames.csv requires; for a perfect set-up ``d = (sin W, 0, -cos W)``.
- The ideal image point is ``q = -f (dx, dy) / dz``, the measured (distorted) point
  ``fieldcal.model.camera.distort(q)``, in pixels through the sensor's mm -> pixel mapping.
- Per angle the true arm angle differs from the encoder's by a random encoder error; per
  frame the image moves by a random jitter (air turbulence, vibration of the arm): both are
  the noise that frame averaging and the fit see, besides the pixel noise.

Spot and noise
--------------
The spot is a core Gaussian plus a wider halo (a blur disc with its diffraction skirt),
stretched by ``1 / cos(field angle)`` along the sweep (the oblique pencil) and dimmed by
``cos^4`` (vignetting). Pixel values are the exact integrals of that profile over each
pixel (differences of the normal CDF at the pixel edges: the profile is separable), which
is what an infinitely fine supersampling would give, so the spot's true centre is known
without sampling error. Then photon noise (Poisson in electrons), a gain, a black level,
Gaussian read noise, rounding to 16-bit and clipping at 65535 DN (saturation).

Cheap frames
------------
Full frames are 21 and 39 megapixels. Two measures keep sessions small and fast, both
chosen so the measurement sees what it would see in a real frame:

- Only a window around the spot (``window_px``) gets the spot and the noise; the rest of
  the frame is the flat mean background (``full_frame_noise=True`` renders noise
  everywhere). Frames are tiled, zstd-compressed 16-bit TIFFs: a full-size frame is about
  20 KB on disk. The measurement still reads and searches the whole frame.
- ``raster_scale`` < 1 renders a coarser pixel grid over the *same* physical sensor and
  lens (same f, principal point and distortion in mm, same angles): ``round(W s) x
  round(H s)`` pixels of ``pixel_size_um / s``. The spot, its noise and the jitter are
  specified in output pixels, so the centroid statistics in pixels are those of the full
  sensor; what shrinks is the distortion in pixels (by ``s``). Tests use ``s = 0.25``
  (frames of 1.3 and 2.4 megapixels).
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import tifffile
from scipy.special import ndtr

from fieldcal.errors import InputError
from fieldcal.model.camera import Camera, Sensor, distort, params_from_dict, unproject
from fieldcal.model.rotations import R_from_rotvec

__all__ = ["Scenario", "SCENARIOS", "FAULTS", "GonioTruth", "make_scenario", "sweep_directions",
           "spot_positions_px", "render_frame", "write_session"]


def _sweep(max_deg: float, step_deg: float) -> tuple[float, ...]:
    n = int(round(max_deg / step_deg))
    return tuple(float(a) for a in np.arange(-n, n + 1) * step_deg)


@dataclass(frozen=True)
class Scenario:
    """A camera on the goniometer: sensor, true lens, sweeps, spot, noise and set-up errors.

    Units are in the names; image-domain quantities (``*_px``, electrons, DN) refer to the
    output pixels (see ``raster_scale`` in the module docstring).
    """

    name: str
    width_px: int
    height_px: int
    pixel_size_um: float
    nominal_focal_mm: float
    params: dict                          # the true camera, fieldcal-brown/1 names
    x_angles_deg: tuple[float, ...]
    y_angles_deg: tuple[float, ...]
    psf_sigma_px: float = 0.9             # core Gaussian of the spot
    halo_sigma_px: float = 2.5            # halo Gaussian
    halo_fraction: float = 0.2            # share of the spot's energy in the halo
    spot_e: float = 2.0e5                 # electrons in the spot on the axis
    background_e: float = 30.0            # electrons per pixel of stray light and dark current
    gain_dn_per_e: float = 1.0
    black_dn: float = 1024.0
    read_noise_dn: float = 4.0
    jitter_px: float = 0.06               # per-frame image motion, each axis [px]
    encoder_sigma_arcsec: float = 1.0     # per-angle encoder error
    align_sigma_px: float = 0.3           # where the encoder zero lands, each axis [px]
    tilt_sigma_mrad: float = 1.5          # inclination of the arm's axis about r0
    cone_sigma_mrad: float = 0.5          # collimator vs arm axis

    def sensor(self) -> Sensor:
        return Sensor(self.width_px, self.height_px, self.pixel_size_um)

    def camera(self) -> Camera:
        return Camera(self.sensor(), params_from_dict(self.params))


SCENARIOS: dict[str, Scenario] = {
    # Canon EOS 5D Mark II with a 24 mm lens: ~20 px of barrel distortion left after the
    # interior orientation on the x sweep (the paper's Fig. 4), +-34 / +-24 deg in 2 deg steps.
    "canon5d2": Scenario(
        name="canon5d2", width_px=5616, height_px=3744, pixel_size_um=6.4, nominal_focal_mm=24.0,
        params={"f_mm": 24.31, "xp_mm": 0.081, "yp_mm": -0.047, "k1": 1.1e-4, "k2": -6e-8,
                "p1": 3e-6, "p2": -2e-6},
        x_angles_deg=_sweep(34, 2), y_angles_deg=_sweep(24, 2)),
    # Hasselblad H3D with a 50 mm lens: under 1 px of distortion, +-22 / +-17 deg in 1 deg steps.
    "h3d": Scenario(
        name="h3d", width_px=7216, height_px=5412, pixel_size_um=6.8, nominal_focal_mm=50.0,
        params={"f_mm": 50.62, "xp_mm": -0.035, "yp_mm": 0.028, "k1": -2e-6, "k2": 8e-9,
                "k3": -4e-12, "p1": 1.5e-6, "p2": -1e-6},
        x_angles_deg=_sweep(22, 1), y_angles_deg=_sweep(17, 1)),
}

FAULTS: tuple[str, ...] = ("missing_file", "no_spot", "saturated", "double", "off_sensor",
                           "bad_axis")
"""Injectable faults: a frame file deleted; a frame without a spot (lamp off); a saturated
spot; a ghost next to the spot; an extra x-sweep angle whose spot falls off the sensor
(all its frames); a frames.csv row with the axis value ``z``."""


def make_scenario(name: str, *, raster_scale: float = 1.0, **overrides) -> Scenario:
    """A named scenario, optionally on a coarser pixel grid and with fields replaced."""
    if name not in SCENARIOS:
        raise InputError(f"unknown scenario {name!r}; known: {sorted(SCENARIOS)}")
    if not (0 < raster_scale <= 1):
        raise InputError(f"raster_scale must be in (0, 1], got {raster_scale}")
    sc = SCENARIOS[name]
    if raster_scale != 1.0:
        sc = dataclasses.replace(
            sc, width_px=int(round(sc.width_px * raster_scale)),
            height_px=int(round(sc.height_px * raster_scale)),
            pixel_size_um=sc.pixel_size_um / raster_scale)
    unknown = set(overrides) - {f.name for f in dataclasses.fields(Scenario)}
    if unknown:
        raise InputError(f"unknown scenario field(s) {sorted(unknown)}")
    return dataclasses.replace(sc, **overrides)


def sweep_directions(axis: str, angles_rad, r0, *, tilt_rad: float = 0.0, cone_rad: float = 0.0):
    """Target directions (n, 3) in the camera frame for arm angles ``angles_rad`` (n,).

    See the module docstring: ``r0`` (3,) is the unit direction of the arm's zero.
    """
    r0 = np.asarray(r0, float) / np.linalg.norm(r0)
    base = np.array([0.0, 1.0, 0.0]) if axis == "x" else np.array([1.0, 0.0, 0.0])
    a0 = base - (base @ r0) * r0
    a0 /= np.linalg.norm(a0)
    a_t = np.cos(tilt_rad) * a0 + np.sin(tilt_rad) * np.cross(r0, a0)
    a = np.cos(cone_rad) * a_t + np.sin(cone_rad) * r0
    sign = -1.0 if axis == "x" else 1.0
    R = R_from_rotvec(sign * np.asarray(angles_rad, float)[:, None] * a)
    return R @ r0


def spot_positions_px(camera: Camera, axis: str, angles_deg, misalignment: dict):
    """Exact measured spot positions (n, 2) [px] of a sweep; NaN where behind the camera.

    ``misalignment``: ``zero_px`` (du, dv) where the encoder zero lands relative to the
    sensor centre, ``tilt_mrad``, ``cone_mrad``.
    """
    s = camera.sensor
    centre = np.array([(s.width_px - 1) / 2.0, (s.height_px - 1) / 2.0])
    r0 = unproject(centre + np.asarray(misalignment["zero_px"], float), camera)
    d = sweep_directions(axis, np.radians(np.asarray(angles_deg, float)), r0,
                         tilt_rad=1e-3 * misalignment["tilt_mrad"],
                         cone_rad=1e-3 * misalignment["cone_mrad"])
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -camera.f_mm * d[:, :2] / np.where(d[:, 2] < 0, d[:, 2], np.nan)[:, None]
    return s.mm_to_pixel(distort(q, camera.params, check=False))


def _field_angle(camera: Camera, uv_px):
    """Angle [rad] between the optical axis and the ray of a measured pixel (n,)."""
    ray = unproject(np.atleast_2d(uv_px), camera)
    return np.arccos(np.clip(-ray[:, 2], -1.0, 1.0))


def render_frame(sc: Scenario, spots, rng, *, noise: bool = True, window_px: int = 20,
                 full_frame_noise: bool = False) -> np.ndarray:
    """One 16-bit frame with the given spots.

    Parameters
    ----------
    sc : Scenario
    spots : sequence of dict
        Each ``{"u_px", "v_px", "flux_e", "sigma_u_px", "sigma_v_px"}``: centre [px], electrons,
        and the core sigma along u and v (the halo is scaled alike).
    rng : numpy.random.Generator
    noise : bool
        Photon and read noise (False: the expected values, rounded).
    window_px : int
        Half-size of the window that gets the spot and the noise [px].
    full_frame_noise : bool
        Noise over the whole frame instead of the windows only.

    Returns
    -------
    (height_px, width_px) uint16 ndarray
    """
    h, w = sc.height_px, sc.width_px
    bg_dn = sc.black_dn + sc.gain_dn_per_e * sc.background_e
    read_total = float(np.hypot(sc.read_noise_dn, sc.gain_dn_per_e * np.sqrt(sc.background_e)))
    if noise and full_frame_noise:
        frame = np.rint(bg_dn + read_total * rng.standard_normal((h, w), dtype=np.float32))
        frame = np.clip(frame, 0, 65535).astype(np.uint16)
    else:
        frame = np.full((h, w), int(round(bg_dn)), np.uint16)
    spots = [s for s in spots if np.isfinite(s["u_px"]) and np.isfinite(s["v_px"])]
    if not spots:
        return frame
    # one window over all spots (a ghost shares the spot's window), clipped to the sensor
    uu = np.floor([s["u_px"] for s in spots]).astype(int)
    vv = np.floor([s["v_px"] for s in spots]).astype(int)
    c0, c1 = max(uu.min() - window_px, 0), min(uu.max() + window_px + 1, w)
    r0, r1 = max(vv.min() - window_px, 0), min(vv.max() + window_px + 1, h)
    if c1 <= c0 or r1 <= r0:
        return frame                                   # off the sensor: nothing to draw
    cols, rows = np.arange(c0, c1, dtype=float), np.arange(r0, r1, dtype=float)
    electrons = np.full((r1 - r0, c1 - c0), float(sc.background_e))
    for s in spots:
        for frac, scale in ((1.0 - sc.halo_fraction, 1.0),
                            (sc.halo_fraction, sc.halo_sigma_px / sc.psf_sigma_px)):
            su, sv = s["sigma_u_px"] * scale, s["sigma_v_px"] * scale
            eu = ndtr((cols + 0.5 - s["u_px"]) / su) - ndtr((cols - 0.5 - s["u_px"]) / su)
            ev = ndtr((rows + 0.5 - s["v_px"]) / sv) - ndtr((rows - 0.5 - s["v_px"]) / sv)
            electrons += s["flux_e"] * frac * np.outer(ev, eu)
    if noise:
        dn = sc.black_dn + sc.gain_dn_per_e * rng.poisson(electrons) \
            + sc.read_noise_dn * rng.standard_normal(electrons.shape)
    else:
        dn = sc.black_dn + sc.gain_dn_per_e * electrons
    frame[r0:r1, c0:c1] = np.clip(np.rint(dn), 0, 65535).astype(np.uint16)
    return frame


@dataclass
class GonioTruth:
    """What :func:`write_session` rendered.

    Attributes
    ----------
    scenario : Scenario
        After ``raster_scale`` and overrides.
    camera : Camera
        The true camera (``camera.sensor`` is the session's sensor).
    folder : Path
        The session folder.
    misalignment : dict
        Per axis: ``zero_px`` [du, dv] (where the encoder zero lands relative to the sensor
        centre), ``tilt_mrad``, ``cone_mrad``, and ``w0_arcsec`` (the along-sweep part of
        ``zero_px`` as an encoder offset).
    frames : pyarrow.Table
        One row per frame listed in frames.csv: ``file, axis, angle_deg, frame``, the
        exact position for the encoder angle ``u_px, v_px`` (no encoder error, no jitter),
        the position the spot was rendered at ``u_rendered_px, v_rendered_px`` (with both),
        ``on_sensor`` and ``fault`` (null, or the injected fault's name).
    faults : list of dict
        Each injected fault: ``fault``, ``file`` (or ``files``), ``axis``, ``angle_deg``.
    """

    scenario: Scenario
    camera: Camera
    folder: Path
    misalignment: dict
    frames: pa.Table
    faults: list = field(default_factory=list)

    @property
    def sensor(self) -> Sensor:
        return self.camera.sensor

    def exact_measurements(self, *, rendered: bool = False) -> pa.Table:
        """A measurements table (as :func:`fieldcal.goniometer.method.measure_frame` rows) holding
        the exact positions: the noise-free data of this set-up (``rendered=False``), or
        the positions the spots were rendered at (with encoder error and jitter)."""
        from fieldcal.goniometer.method import measurements_table

        u = self.frames["u_rendered_px" if rendered else "u_px"].to_numpy()
        v = self.frames["v_rendered_px" if rendered else "v_px"].to_numpy()
        on = self.frames["on_sensor"].to_numpy(zero_copy_only=False)
        rows = [{"file": f, "u_px": float(uu), "v_px": float(vv),
                 "flag": "ok" if ok else "missing", "reason": "" if ok else "off the sensor"}
                for f, uu, vv, ok in zip(self.frames["file"].to_pylist(), u, v, on, strict=True)]
        return measurements_table(rows)


def _misalignment(sc: Scenario, rng, given: dict | None) -> dict:
    out = {}
    for axis in ("x", "y"):
        m = {"zero_px": [float(x) for x in rng.normal(0.0, sc.align_sigma_px, 2)],
             "tilt_mrad": float(rng.normal(0.0, sc.tilt_sigma_mrad)),
             "cone_mrad": float(rng.normal(0.0, sc.cone_sigma_mrad))}
        if given and axis in given:
            unknown = set(given[axis]) - set(m)
            if unknown:
                raise InputError(f"misalignment[{axis!r}]: unknown key(s) {sorted(unknown)}")
            m.update(given[axis])
        along = m["zero_px"][0] if axis == "x" else -m["zero_px"][1]
        m["w0_arcsec"] = float(np.degrees(along * sc.pixel_size_um * 1e-3 / sc.params["f_mm"]) * 3600)
        out[axis] = m
    return out


def _off_sensor_angle(sc: Scenario, cam: Camera, mis: dict) -> float:
    """The first x-sweep angle past the last one whose spot lands >= 20 px off the sensor."""
    step = sc.x_angles_deg[1] - sc.x_angles_deg[0]
    a = max(sc.x_angles_deg)
    for _ in range(200):
        a += step
        uv = spot_positions_px(cam, "x", [a], mis["x"])[0]
        if not np.isfinite(uv[0]) or uv[0] > sc.width_px - 1 + 20:
            return float(a)
    raise InputError("no off-sensor angle found for the 'off_sensor' fault")


def write_session(folder, scenario: str = "canon5d2", *, seed: int = 0,
                  raster_scale: float = 1.0, frames_per_angle: int = 3, faults=(),
                  noise: bool = True, window_px: int = 20, full_frame_noise: bool = False,
                  misalignment: dict | None = None, camera_id: str | None = None,
                  session_id: str | None = None, **overrides) -> GonioTruth:
    """Render a complete goniometer session (docs/conventions.md section 3) into ``folder``.

    Writes ``session.json`` (schema fieldcal.session/1, method goniometer), ``frames.csv``
    and ``images/<axis>_<angle>_<k>.tif`` (16-bit, tiled, zstd).

    Parameters
    ----------
    folder : path-like
        Created if needed; existing files of the same names are overwritten.
    scenario : {"canon5d2", "h3d"}
        The name of a scenario in :data:`SCENARIOS`.
    seed : int
        Seeds everything random (set-up errors, encoder errors, jitter, noise).
    raster_scale : float
        Coarser pixel grid over the same sensor and lens (module docstring).
    frames_per_angle : int
        Repeated frames at every angle.
    faults : iterable of str
        Names from :data:`FAULTS` to inject.
    noise : bool
        Photon and read noise in the pixels (jitter and encoder errors are scenario
        fields: pass ``jitter_px=0, encoder_sigma_arcsec=0`` to remove them).
    window_px, full_frame_noise
        See :func:`render_frame`.
    misalignment : dict, optional
        Per axis, values that replace the random set-up errors (keys ``zero_px``,
        ``tilt_mrad``, ``cone_mrad``).
    camera_id, session_id : str, optional
        Defaults: ``"<scenario>-synthetic"`` and the folder's name.
    **overrides
        Scenario fields to replace (e.g. ``jitter_px=0.0``).

    Returns
    -------
    GonioTruth
    """
    folder = Path(folder)
    faults = tuple(faults)
    bad = [f for f in faults if f not in FAULTS]
    if bad:
        raise InputError(f"unknown fault(s) {bad}; known: {list(FAULTS)}")
    if frames_per_angle < 1:
        raise InputError(f"frames_per_angle must be >= 1, got {frames_per_angle}")
    sc = make_scenario(scenario, raster_scale=raster_scale, **overrides)
    cam = sc.camera()
    rng = np.random.default_rng(seed)
    mis = _misalignment(sc, rng, misalignment)
    (folder / "images").mkdir(parents=True, exist_ok=True)

    sweeps = {"x": list(sc.x_angles_deg), "y": list(sc.y_angles_deg)}
    if "off_sensor" in faults:
        sweeps["x"].append(_off_sensor_angle(sc, cam, mis))
    by_frame = _fault_frames(sc, faults, frames_per_angle)

    rows, truth_faults = _render_sweeps(folder, sc, cam, mis, sweeps, by_frame, faults, rng,
                                        frames_per_angle, noise, window_px, full_frame_noise)
    _write_manifest(folder, sc, rows, camera_id, session_id)
    frames = pa.Table.from_pylist(rows, schema=pa.schema([
        ("file", pa.string()), ("axis", pa.string()), ("angle_deg", pa.float64()),
        ("frame", pa.int32()), ("u_px", pa.float64()), ("v_px", pa.float64()),
        ("u_rendered_px", pa.float64()), ("v_rendered_px", pa.float64()),
        ("on_sensor", pa.bool_()), ("fault", pa.string())]))
    return GonioTruth(sc, cam, folder, mis, frames, truth_faults)


def _fault_frames(sc: Scenario, faults, frames_per_angle: int) -> dict:
    """Which frame ``(axis, angle, k)`` gets which single-frame fault: distinct angles on both
    sweeps."""
    nx, ny = len(sc.x_angles_deg), len(sc.y_angles_deg)
    targets = {"missing_file": ("x", sc.x_angles_deg[nx // 2 + 3], 0),
               "no_spot": ("x", sc.x_angles_deg[nx // 2 - 4], 1 % frames_per_angle),
               "saturated": ("y", sc.y_angles_deg[ny // 2 + 2], 0),
               "double": ("y", sc.y_angles_deg[ny // 2 - 3], 2 % frames_per_angle),
               "bad_axis": ("x", sc.x_angles_deg[nx // 2 + 5], 2 % frames_per_angle)}
    return {targets[f]: f for f in faults if f in targets}


def _spots_of(spot: dict, fault, axis: str) -> list:
    """The spots of one frame: the collimator's, changed by the frame's fault."""
    if fault == "no_spot":
        return []
    if fault == "saturated":
        return [dict(spot, flux_e=spot["flux_e"] * 40.0)]
    if fault == "double":
        ghost = dict(spot, flux_e=spot["flux_e"] * 0.5)
        ghost["u_px" if axis == "y" else "v_px"] += 9.0
        return [spot, ghost]
    return [spot]


def _write_manifest(folder: Path, sc: Scenario, rows, camera_id, session_id) -> None:
    """frames.csv (a ``bad_axis`` frame gets the axis ``z``) and session.json."""
    lines = ["file,axis,angle_deg"]
    for r in rows:
        axis = "z" if r["fault"] == "bad_axis" else r["axis"]
        lines.append(f"{r['file']},{axis},{r['angle_deg']:.6f}")
    (folder / "frames.csv").write_text("\n".join(lines) + "\n")
    manifest = {
        "schema": "fieldcal.session/1",
        "method": "goniometer",
        "camera_id": camera_id or f"{sc.name}-synthetic",
        "session_id": session_id or folder.name,
        "acquired": "2026-11-20T09:30:00Z",
        "sensor": sc.sensor().to_dict(),
        "lens": {"nominal_focal_mm": sc.nominal_focal_mm},
        "frames": "frames.csv",
        "images": "images/*.tif",
    }
    (folder / "session.json").write_text(json.dumps(manifest, indent=2) + "\n")


def _render_sweeps(folder, sc, cam, mis, sweeps, by_frame, faults, rng, frames_per_angle, noise, window_px,
                   full_frame_noise):
    """Render and write every frame of both sweeps; returns the frames' rows and the faults."""
    rows = []
    truth_faults = []
    arcsec = np.radians(1.0 / 3600.0)
    for axis in ("x", "y"):
        angles = np.asarray(sweeps[axis], float)
        exact = spot_positions_px(cam, axis, angles, mis[axis])
        enc_err_deg = np.degrees(rng.normal(0.0, sc.encoder_sigma_arcsec * arcsec, angles.size))
        true_pos = spot_positions_px(cam, axis, angles + enc_err_deg, mis[axis])
        theta = _field_angle(cam, np.nan_to_num(true_pos, nan=0.0))
        for i, a in enumerate(angles):
            on = bool(np.all(np.isfinite(exact[i]))
                      and -0.5 <= exact[i, 0] <= sc.width_px - 0.5
                      and -0.5 <= exact[i, 1] <= sc.height_px - 0.5)
            for k in range(frames_per_angle):
                name = f"images/{axis}_{a:+06.2f}_{k}.tif"
                jit = rng.normal(0.0, sc.jitter_px, 2)
                u, v = true_pos[i] + jit
                stretch = 1.0 / np.cos(theta[i])
                spot = {"u_px": u, "v_px": v, "flux_e": sc.spot_e * np.cos(theta[i]) ** 4,
                        "sigma_u_px": sc.psf_sigma_px * (stretch if axis == "x" else 1.0),
                        "sigma_v_px": sc.psf_sigma_px * (stretch if axis == "y" else 1.0)}
                fault = by_frame.get((axis, float(a), k))
                if axis == "x" and "off_sensor" in faults and a == sweeps["x"][-1]:
                    fault = "off_sensor"
                frame = render_frame(sc, _spots_of(spot, fault, axis), rng, noise=noise, window_px=window_px,
                                     full_frame_noise=full_frame_noise)
                path = folder / name
                tifffile.imwrite(path, frame, tile=(256, 256), compression="zstd")
                if fault == "missing_file":
                    os.remove(path)
                rows.append({"file": name, "axis": axis, "angle_deg": float(a), "frame": k,
                             "u_px": float(exact[i, 0]), "v_px": float(exact[i, 1]),
                             "u_rendered_px": float(u), "v_rendered_px": float(v),
                             "on_sensor": on, "fault": fault})
                if fault and fault != "off_sensor":
                    truth_faults.append({"fault": fault, "file": name, "axis": axis,
                                         "angle_deg": float(a)})
    if "off_sensor" in faults:
        a = sweeps["x"][-1]
        truth_faults.append({"fault": "off_sensor", "axis": "x", "angle_deg": a,
                             "files": [r["file"] for r in rows
                                       if r["axis"] == "x" and r["angle_deg"] == a]})

    return rows, truth_faults
