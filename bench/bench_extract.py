"""Benchmark: target extraction on one full-size 8208 x 6280 16-bit frame with ~2000 discs.

Usage::

    python bench/bench_extract.py [--workdir DIR] [--repeat N] [--markdown FILE]
                                  [--eccentricity] [--methods]

What it does, in one run (``OPENBLAS_NUM_THREADS=1``):

1. Renders (once; cached in ``--workdir``) a dense planar field seen square-on by the
   paper's camera (IXU150-like, 5.3 um, Table 1 distortion) from 60 m: a 52 x 40 grid of
   60 mm dark discs (~28 px) filling the frame, PSF sigma 0.8 px, shot and read noise
   (``fieldcal.synthetic.render.render_image``), written as an uncompressed TIFF, a zstd
   TIFF and in each layout of the renderer's TIFF mix.
2. Extraction with the pixels in memory, all stages, in one process, interleaved round by
   round: the floor (one NumPy pass, ``arr.max()``, best of 5 per round), the NumPy
   reference (``engine="numpy"``), the Numba kernel (``engine="numba"``, loaded from its
   cache before the first round) and ``cv2.SimpleBlobDetector`` with default settings
   (three rounds; with and without its 16 -> 8 bit conversion); best times, ratios to the
   floor (best over best, and the median of each round's ratio), accuracy of each against
   the renderer's exact image of each disc's centre (discs seen square-on: no perspective
   eccentricity beyond the renderer's tiny distortion term; the exact ellipse centre is in
   the truth too).
3. Peak resident memory in a fresh process per engine and file (``VmHWM``, reset between
   the read and the extraction): of reading, of extracting (above the image) and of the
   two, relative to the image's size.
4. Per image of the renderer's TIFF mix, interleaved: read + hash + decode + extract as
   the flow did before (hash the file, read it again, decode with one thread, NumPy
   extraction) and as it does now (one read that hashes the bytes, decode from them with
   1 or 2 codec threads, the Numba kernel). The files are in the page cache.
5. Optionally the eccentricity in the two synthetic scenarios (``--eccentricity``) and a
   comparison of the two centre methods and SimpleBlobDetector on rendered images of
   both scenarios (``--methods``).

Prints the results tables (markdown) and, with ``--markdown FILE``, writes them there
(bench/README_extract.md holds a commented copy).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GRID = (52, 40)
DISTANCE_M = 60.0


def dense_field():
    """A SyntheticField: one image of a planar grid of discs filling the frame."""
    from fieldcal.model.camera import Camera, Sensor
    from fieldcal.session.data import FieldData, FieldImage, FieldObservations, TargetField
    from fieldcal.synthetic.field import IXU150_TABLE1, SyntheticField, look_at

    cam = Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1)
    # the frame covers about 8208 * 5.3e-3 / 146.39 * 60 = 17.8 m x 13.6 m at 60 m
    nx, nz = GRID
    xs = (np.arange(nx) - (nx - 1) / 2) * (17.0 / nx)
    zs = (np.arange(nz) - (nz - 1) / 2) * (13.0 / nz)
    rng = np.random.default_rng(7)
    xx, zz = np.meshgrid(xs, zs)
    xx = xx.ravel() + rng.uniform(-0.05, 0.05, xx.size)     # random sub-pixel phases
    zz = zz.ravel() + rng.uniform(-0.05, 0.05, zz.size)
    xyz = np.stack([xx, np.zeros_like(xx), zz + 15.0], axis=1)
    n = len(xyz)
    targets = TargetField([f"D{i:04d}" for i in range(n)], xyz, 5.0, -1,
                          np.tile([0.0, -1.0, 0.0], (n, 1)))
    C = np.array([0.0, -DISTANCE_M, 15.0])
    R = look_at(C, np.array([0.0, 0.0, 15.0]))
    uv = cam.project(xyz, R, C)
    data = FieldData(cam.sensor, targets, [FieldImage("images/dense.tif")],
                     FieldObservations(np.zeros(n, int), np.arange(n), uv, 0.1))
    return SyntheticField("dense", cam, targets, R[None], C[None], uv, data, 60.0, 400.0,
                          {"scenario": "paper"})


def make_images(workdir: Path):
    import tifffile

    from fieldcal.synthetic.render import render_image

    workdir.mkdir(parents=True, exist_ok=True)
    raw, zst, truth_p = workdir / "dense.tif", workdir / "dense_zstd.tif", workdir / "truth.pkl"
    if raw.exists() and zst.exists() and truth_p.exists():
        return raw, zst, truth_p
    t0 = time.perf_counter()
    r = render_image(dense_field(), 0, psf_sigma_px=0.8, seed=1)
    print(f"rendered {r.pixels.shape} with {r.truth.num_rows} targets in "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    tifffile.imwrite(raw, r.pixels, photometric="minisblack", metadata=None)
    tifffile.imwrite(zst, r.pixels, photometric="minisblack", metadata=None, compression="zstd",
                     tile=(512, 512))
    with open(truth_p, "wb") as fh:
        pickle.dump({k: v for k, v in r.truth.to_pydict().items() if k != "corners_px"}, fh)
    return raw, zst, truth_p


# the renderer's mix of TIFF layouts (fieldcal.synthetic.session_writer.write_field_session with
# compression_mix=True: image k uses layout k mod 4)
MIX = (
    ("tiled 256, zstd", {"tile": (256, 256), "compression": "zstd", "bigtiff": False}),
    ("striped, uncompressed", {"rowsperstrip": 64, "bigtiff": False}),
    ("tiled 256, deflate, BigTIFF", {"tile": (256, 256), "compression": "adobe_deflate", "bigtiff": True}),
    ("striped, uncompressed, BigTIFF", {"rowsperstrip": 64, "bigtiff": True}),
)


def make_mix(workdir: Path, raw: Path) -> list[Path]:
    """The dense frame written in each layout of the renderer's mix (once; cached)."""
    import tifffile

    paths = [workdir / f"mix_{k}.tif" for k in range(len(MIX))]
    if all(p.exists() for p in paths):
        return paths
    pixels = tifffile.imread(raw)
    for p, (_, kw) in zip(paths, MIX, strict=True):
        tifffile.imwrite(p, pixels, photometric="minisblack", metadata=None, **kw)
    return paths


# --------------------------------------------------------------------------------------
# measurements, each in a fresh process
# --------------------------------------------------------------------------------------
DETECT = {"polarity": "dark", "min_diameter_px": 16, "max_diameter_px": 48}


def _status_mb(key):
    # VmHWM is this process image's peak RSS (getrusage's maxrss survives fork + exec, so a
    # child of a big parent would report the parent's peak)
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak():
    """Reset VmHWM to the current RSS (Linux >= 4.0: ``clear_refs`` 5)."""
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _timed_cpu(fn):
    """(wall time, CPU time of the process: every thread's, none of the waits) [s], result."""
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    return (time.perf_counter() - t0, time.process_time() - c0), out


def _child_timing(path: str, rounds: int) -> dict:
    """Floor, NumPy reference, Numba kernel and SimpleBlobDetector, interleaved round by round."""
    import cv2

    from fieldcal.measure import disc_kernel
    from fieldcal.measure.coded import to_uint8
    from fieldcal.measure.discs import detect_targets
    from fieldcal.measure.imageio import read_image

    assert disc_kernel.warm_up(), disc_kernel.problem()
    arr = read_image(path)
    res = {k: [] for k in ("max", "numpy", "numba", "blob", "to_uint8")}
    cpu = {k: [] for k in ("max", "numpy", "numba")}       # this thread's CPU time: not the waits
    tables = {}
    for r in range(rounds):
        best = (np.inf, np.inf)
        for _ in range(5):
            c0 = time.thread_time()
            t, _ = _timed(arr.max)
            best = (min(best[0], t), min(best[1], time.thread_time() - c0))
        res["max"].append(best[0])
        cpu["max"].append(best[1])
        for engine in ("numpy", "numba"):
            c0 = time.thread_time()
            t, tables[engine] = _timed(lambda e=engine: detect_targets(arr, engine=e, **DETECT))
            cpu[engine].append(time.thread_time() - c0)
            res[engine].append(t)
        if r < 3:                                  # ~2 s each: three rounds are enough
            t8, img8 = _timed_cpu(lambda: to_uint8(arr))
            tb, kps = _timed_cpu(lambda i=img8: cv2.SimpleBlobDetector_create().detect(i))
            res["to_uint8"].append(t8[0])
            res["blob"].append(tb[0])
            cpu.setdefault("blob", []).append(tb[1] + t8[1])
    out = {"times": res, "cpu": cpu, "image_mb": arr.nbytes / 2**20, "cv2_threads": cv2.getNumThreads(),
           "blob_uv": [list(k.pt) for k in kps]}
    for engine, table in tables.items():
        out[engine] = {"uv": np.stack([table["u_px"].to_numpy(), table["v_px"].to_numpy()], 1).tolist(),
                       "truncated": table["truncated"].to_numpy(zero_copy_only=False).tolist(),
                       "sigma_px": table["sigma_px"].to_numpy().tolist()}
    return out


def _child_peak(path: str, how: str) -> dict:
    """Peak resident memory of reading one image, then of extracting its targets.

    ``how``: ``"before"`` (the file read by path, NumPy reference) or ``"after"`` (one read
    that hashes the bytes, ``read_file``, decoded from them; the Numba kernel).
    """
    from fieldcal.measure import disc_kernel
    from fieldcal.measure.discs import detect_targets
    from fieldcal.measure.imageio import read_file, read_image

    before = _status_mb("VmRSS")
    if how == "after":
        assert disc_kernel.warm_up(), disc_kernel.problem()
    base = _status_mb("VmRSS")
    _reset_peak()
    source = read_file(path) if how == "after" else path
    arr = read_image(source)
    read_peak = _status_mb("VmHWM")
    after_read = _status_mb("VmRSS")
    _reset_peak()
    detect_targets(arr, engine="numba" if how == "after" else "numpy", **DETECT)
    return {"image_mb": arr.nbytes / 2**20, "kernel_mb": base - before, "base_mb": base,
            "read_peak_mb": read_peak - base, "after_read_mb": after_read - base,
            "extract_peak_mb": _status_mb("VmHWM") - base}


def _child_per_image(paths: list[str], rounds: int) -> dict:
    """Per image of the renderer's TIFF mix: read + hash + decode + extract, before and after.

    Before: the file hashed (``sha256_file``), then read again and decoded with one codec
    thread, extraction by the NumPy reference. After: one read that hashes the bytes on the
    way (``read_file``), decoding from those bytes with 1 or 2 codec threads, extraction
    by the Numba kernel.
    """
    from fieldcal.contract.fingerprint import sha256_file
    from fieldcal.measure import disc_kernel
    from fieldcal.measure.discs import detect_targets
    from fieldcal.measure.imageio import read_file, read_image

    assert disc_kernel.warm_up(), disc_kernel.problem()

    def before(p):
        t_hash, _ = _timed_cpu(lambda: sha256_file(p))
        t_dec, arr = _timed_cpu(lambda: read_image(p, maxworkers=1))
        t_ext, _ = _timed_cpu(lambda: detect_targets(arr, engine="numpy", **DETECT))
        return {"hash": t_hash, "read+decode": t_dec, "extract": t_ext}

    def after(p, threads):
        t_read, f = _timed_cpu(lambda: read_file(p))
        t_dec, arr = _timed_cpu(lambda: read_image(f, maxworkers=threads))
        t_ext, _ = _timed_cpu(lambda: detect_targets(arr, engine="numba", **DETECT))
        return {"read+hash": t_read, "decode": t_dec, "extract": t_ext}

    runs = {"before": before, "after, 1 codec thread": lambda p: after(p, 1),
            "after, 2 codec threads": lambda p: after(p, 2)}
    out = {str(k): {name: [] for name in runs} for k in range(len(paths))}
    for _ in range(rounds):
        for k, p in enumerate(paths):
            for name, fn in runs.items():
                out[str(k)][name].append(fn(p))
    return out


def _child(task: str, args: list[str], repeat: int) -> dict:
    if task == "timing":
        return _child_timing(args[0], repeat)
    if task == "peak":
        return _child_peak(args[0], args[1])
    if task == "per_image":
        return _child_per_image(args, repeat)
    raise ValueError(task)


def run_child(task, args, repeat):
    cmd = [sys.executable, __file__, "--child", task, *map(str, args), "--repeat", str(repeat)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=os.environ.copy())
    return json.loads(res.stdout.strip().splitlines()[-1])


def accuracy(uv, truth, exclude_truncated=None):
    from scipy.spatial import cKDTree

    uv = np.asarray(uv, float).reshape(-1, 2)
    inside = np.asarray(truth["fully_inside"], bool) & (np.asarray(truth["kind"]) == "disc")
    ut = np.stack([truth["u_px"], truth["v_px"]], 1)
    ue = np.stack([truth["u_ellipse_px"], truth["v_ellipse_px"]], 1)
    if exclude_truncated is not None:
        uv_acc = uv[~np.asarray(exclude_truncated, bool)]
    else:
        uv_acc = uv
    d, j = cKDTree(uv).query(ut, distance_upper_bound=3.0)
    found = np.isfinite(d)
    d2, j2 = cKDTree(uv_acc).query(ut, distance_upper_bound=3.0)
    ok = inside & np.isfinite(d2)
    e_c = uv_acc[j2[ok]] - ut[ok]
    e_e = uv_acc[j2[ok]] - ue[ok]
    matched = set(j[found].tolist())
    return {
        "n_truth_inside": int(inside.sum()),
        "detected": float(found[inside].mean()),
        "false": int(len(uv) - len(matched)),
        "rms_centre_px": float(np.sqrt(np.mean(np.sum(e_c**2, 1)))),
        "rms_ellipse_px": float(np.sqrt(np.mean(np.sum(e_e**2, 1)))),
        "max_centre_px": float(np.max(np.linalg.norm(e_c, axis=1))),
    }


def eccentricity_table():
    """Size of the perspective eccentricity in the two synthetic scenarios (true poses)."""
    from fieldcal.field.eccentricity import correction_px
    from fieldcal.synthetic.field import paper_field, wide_field

    rows = []
    for sf in (paper_field(), wide_field()):
        obs = sf.data.obs
        mags = []
        for i in range(len(sf.R_world_to_camera)):
            k = obs.target[obs.image == i]
            if k.size == 0:
                continue
            c = correction_px(sf.camera, sf.R_world_to_camera[i], sf.center_m[i],
                              sf.targets_true.xyz_m[k], sf.targets_true.normals[k],
                              sf.target_diameter_mm / 2000.0)
            mags.append(np.linalg.norm(c, axis=1))
        m = np.concatenate(mags)
        rows.append((sf.name, sf.target_diameter_mm, m.size, np.median(m), np.percentile(m, 95),
                     m.max()))
    return rows


def methods_table():
    """Both centre methods (and SimpleBlobDetector) on rendered images of both scenarios.

    Paper scenario at raster scale 0.25 (discs ~27 px), wide at 0.5 (~18 px): normal
    exposure (SNR ~95), a dim one (SNR ~15) and a noise-free one. RMS against the exact
    ellipse centre of the well-exposed, untruncated discs that do not touch a marker.
    """
    from scipy.spatial import cKDTree

    from fieldcal.measure.coded import detect_aruco, marker_exclusion_polygons
    from fieldcal.measure.discs import detect_targets, inside_polygons
    from fieldcal.synthetic.field import paper_field, wide_field
    from fieldcal.synthetic.render import render_image, scaled_field
    from tests.measure.peers import opencv_blob_centres

    cases = [("paper x0.25, img 5", "paper", 0.25, 5, {}), ("paper x0.25, img 13", "paper", 0.25, 13, {}),
             ("paper x0.25, dim (SNR ~15)", "paper", 0.25, 5, {"exposure": 0.02}),
             ("paper x0.25, noise-free", "paper", 0.25, 5, {"noise": False}),
             ("wide x0.5, img 7", "wide", 0.5, 7, {})]
    fields = {}
    rows = []
    for label, scen, scale, i, kw in cases:
        if (scen, scale) not in fields:
            fields[scen, scale] = scaled_field(paper_field() if scen == "paper" else wide_field(), scale)
        sf = fields[scen, scale]
        r = render_image(sf, i, seed=5, **kw)
        tr = {k: np.asarray(v) for k, v in r.truth.to_pydict().items() if k != "corners_px"}
        markers = detect_aruco(r.pixels)
        polys = marker_exclusion_polygons(markers)
        disc = (tr["kind"] == "disc") & tr["fully_inside"]
        ell = np.stack([tr["u_ellipse_px"], tr["v_ellipse_px"]], 1)
        if polys:
            near = inside_polygons(ell[:, 0], ell[:, 1], [p * 1.0 for p in polys])
            disc &= ~near
        out = [label, f"{int(disc.sum())}", f"{np.median(tr['snr'][disc]):.0f}"]
        for method in ("ellipse", "centroid"):
            t = detect_targets(r.pixels, method=method, min_diameter_px=10, exclude=polys or None)
            t = t.filter(~np.asarray(t["truncated"].to_numpy(zero_copy_only=False)))
            uv = np.stack([t["u_px"].to_numpy(), t["v_px"].to_numpy()], 1)
            d, j = cKDTree(uv).query(ell, distance_upper_bound=2.0)
            ok = disc & np.isfinite(d)
            e = uv[j[ok]] - ell[ok]
            out.append(f"{np.sqrt(np.mean(np.sum(e**2, 1))):.4f} ({ok.sum() / disc.sum() * 100:.0f} %)")
        ocv = opencv_blob_centres(r.pixels)
        d, j = cKDTree(ocv).query(ell, distance_upper_bound=2.0)
        ok = disc & np.isfinite(d)
        e = ocv[j[ok]] - ell[ok]
        out.append(f"{np.sqrt(np.mean(np.sum(e**2, 1))):.4f} ({ok.sum() / disc.sum() * 100:.0f} %)")
        rows.append("| " + " | ".join(out) + " |")
    head = ["", "| rendered image | discs | SNR | ellipse (default) | centroid (paper, upsample 4) | "
            "SimpleBlobDetector |", "|---|---|---|---|---|---|"]
    return "\n".join(head + rows) + "\n"


def _ms(x):
    return f"{1e3 * x:.1f}" if x < 0.1 else f"{1e3 * x:.0f}"


def timing_table(tm, truth):
    """The extraction table: floor, the two engines, SimpleBlobDetector; ratios; accuracy."""
    t = {k: np.asarray(v) for k, v in tm["times"].items()}
    c = {k: np.asarray(v) for k, v in tm["cpu"].items()}
    floor = t["max"].min()
    rounds = len(t["max"])
    ratio = {e: np.median(t[e] / t["max"]) for e in ("numpy", "numba")}
    acc = {e: accuracy(tm[e]["uv"], truth, tm[e]["truncated"]) for e in ("numpy", "numba")}
    acc_b = accuracy(tm["blob_uv"], truth)
    blob = t["blob"].min() + t["to_uint8"].min()
    a, b = acc["numpy"], acc["numba"]
    return [
        "| quantity | NumPy reference | Numba kernel (default) | SimpleBlobDetector |",
        "|---|---|---|---|",
        f"| image | 8208 x 6280 uint16 ({tm['image_mb']:.0f} MiB), {a['n_truth_inside']} discs fully inside, "
        "~28 px, PSF sigma 0.8 px, SNR ~95 | | |",
        f"| one NumPy pass `arr.max()` (floor), best of {rounds} rounds x 5 | {_ms(floor)} ms | | |",
        f"| extraction, pixels in memory, all stages, best of {rounds} | {_ms(t['numpy'].min())} ms | "
        f"{_ms(t['numba'].min())} ms | {_ms(t['blob'].min())} ms (+ {_ms(t['to_uint8'].min())} ms 16->8 bit) |",
        f"| ratio to the floor (best / best) | {t['numpy'].min() / floor:.1f} x | {t['numba'].min() / floor:.1f} x "
        f"| {blob / floor:.0f} x |",
        f"| ratio to the floor (median of the rounds' ratios) | {ratio['numpy']:.1f} x | {ratio['numba']:.1f} x | |",
        f"| kernel / reference (median of the rounds) | | {np.median(t['numba'] / t['numpy']):.2f} | |",
        f"| CPU time of the thread, best of {rounds} (floor {_ms(c['max'].min())} ms): what the load "
        "does not inflate | "
        f"{_ms(c['numpy'].min())} ms = {c['numpy'].min() / c['max'].min():.1f} x | "
        f"{_ms(c['numba'].min())} ms = {c['numba'].min() / c['max'].min():.1f} x | "
        f"{_ms(c['blob'].min())} ms (process, with the stretch) |",
        f"| detected (fully inside) | {a['detected'] * 100:.2f} % | {b['detected'] * 100:.2f} % | "
        f"{acc_b['detected'] * 100:.2f} % |",
        f"| false detections | {a['false']} | {b['false']} | {acc_b['false']} |",
        f"| RMS error vs exact image of the centre | {a['rms_centre_px']:.4f} px | {b['rms_centre_px']:.4f} px | "
        f"{acc_b['rms_centre_px']:.4f} px |",
        f"| RMS error vs exact ellipse centre | {a['rms_ellipse_px']:.4f} px | {b['rms_ellipse_px']:.4f} px | "
        f"{acc_b['rms_ellipse_px']:.4f} px |",
        f"| max error vs centre | {a['max_centre_px']:.4f} px | {b['max_centre_px']:.4f} px | "
        f"{acc_b['max_centre_px']:.4f} px |",
        f"| largest difference of a centre, kernel vs reference | | "
        f"{np.max(np.abs(np.asarray(tm['numba']['uv']) - np.asarray(tm['numpy']['uv']))):.1e} px | |",
        f"| median a-priori sigma_px (per axis) | {np.median(tm['numpy']['sigma_px']):.4f} px | "
        f"{np.median(tm['numba']['sigma_px']):.4f} px | |",
        f"| OpenCV threads | {tm['cv2_threads']} | | |",
    ]


def peak_table(peaks):
    rows = ["| peak resident memory (x the image) | read | extraction (above the image) | "
            "read + extraction | the kernel's code (MiB) |", "|---|---|---|---|---|"]
    what = {"before": "read by path, NumPy reference", "after": "read once + hashed (`read_file`), Numba kernel"}
    for (label, how), pk in peaks.items():
        img = pk["image_mb"]
        rows.append(f"| {label}, {what[how]} | {pk['read_peak_mb'] / img:.2f} x | "
                    f"{(pk['extract_peak_mb'] - pk['after_read_mb']) / img:.2f} x | "
                    f"{max(pk['read_peak_mb'], pk['extract_peak_mb']) / img:.2f} x | "
                    f"{pk['kernel_mb']:.0f} |")
    return rows


def per_image_table(per):
    rows = ["| layout (renderer's mix) | before: hash + read/decode + extract (NumPy) | "
            "after: read+hash + decode + extract (Numba), 1 codec thread | same, 2 codec threads | "
            "after (1 thread) / before |", "|---|---|---|---|---|"]
    for clock, label_clock in ((0, "wall"), (1, "CPU of the process")):
        for k, (label, _) in enumerate(MIX):
            cells, totals = [], {}
            for name in ("before", "after, 1 codec thread", "after, 2 codec threads"):
                runs = per[str(k)][name]
                parts = {p: min(r[p][clock] for r in runs) for p in runs[0]}
                totals[name] = min(sum(v[clock] for v in r.values()) for r in runs)
                cells.append(" + ".join(_ms(v) for v in parts.values()) + f" = **{_ms(totals[name])} ms**")
            rows.append(f"| {label} ({label_clock}) | {cells[0]} | {cells[1]} | {cells[2]} | "
                        f"{totals['after, 1 codec thread'] / totals['before']:.2f} |")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default="/tmp/fieldcal_bench_extract")
    ap.add_argument("--repeat", type=int, default=9, help="interleaved rounds")
    ap.add_argument("--markdown", default=None, help="write the results table to this file")
    ap.add_argument("--eccentricity", action="store_true", help="add the eccentricity table")
    ap.add_argument("--methods", action="store_true",
                    help="add the table comparing the centre methods on rendered images")
    ap.add_argument("--child", nargs="+", metavar="ARG", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        res = _child(args.child[0], args.child[1:], args.repeat)
        print(json.dumps(res))
        return 0

    workdir = Path(args.workdir)
    raw, zst, truth_p = make_images(workdir)
    mix = make_mix(workdir, raw)
    with open(truth_p, "rb") as fh:
        truth = pickle.load(fh)
    tm = run_child("timing", [raw], args.repeat)
    peaks = {(label, how): run_child("peak", [path, how], 1)
             for label, path in (("uncompressed", raw), ("zstd tiled 512", zst)) for how in ("before", "after")}
    per = run_child("per_image", mix, max(3, args.repeat // 3))
    lines = timing_table(tm, truth) + [""] + peak_table(peaks) + [""] + per_image_table(per)
    text = "\n".join(lines) + "\n"
    if args.eccentricity:
        ecc = ["", "| scenario | disc | pairs | median | 95 % | max |", "|---|---|---|---|---|---|"]
        for name, dmm, n, med, p95, mx in eccentricity_table():
            ecc.append(f"| {name} | {dmm:.0f} mm | {n} | {med:.4f} px | {p95:.4f} px | {mx:.4f} px |")
        text += "\n".join(ecc) + "\n"
    if args.methods:
        text += methods_table()
    print(text)
    t = tm["times"]
    for k in ("max", "numpy", "numba"):
        print(k, "per round:", [round(x * 1e3, 1) for x in t[k]], "ms", file=sys.stderr)
    if args.markdown:
        Path(args.markdown).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
