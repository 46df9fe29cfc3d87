"""Digests of the calibration documents of four test sessions (issue 25, goal 7).

A module move or a refactoring must change no result: run this before and after and
compare the printed lines (``diff``). Each session is calibrated from scratch and committed
to a temporary lake; the digest covers what the lake stored (the document, every Zarr
array with its attributes, the residual table) and the document the solver returned,
with the keys that legitimately differ between runs removed (times of the run, version
ids, the code version; a rig's head versions).

Sessions: a field session from observations with the targets adjusted, a field session
from rendered images (coded targets), a goniometer session and a two-head rig session.

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/documents_digest.py
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

GRID = {"correction_field", "grid_u_px", "grid_v_px"}
"""Stored (the ``zarr`` digest) whether the lake or the solve step computes them."""
VOLATILE = {"created", "version", "code_version", "committed", "head_versions", "versions", "rig_version"}


def _clean(x):
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in sorted(x.items()) if k not in VOLATILE}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, float):
        return x.hex()
    return x


def _digest_json(x) -> str:
    return hashlib.sha256(json.dumps(_clean(x), sort_keys=True, default=str).encode()).hexdigest()[:16]


def _digest_zarr(group) -> str:
    h = hashlib.sha256()
    for name in sorted(group.array_keys()):
        a = np.asarray(group[name][...])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
        h.update(json.dumps(_clean(dict(group[name].attrs)), sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def _digest_table(t) -> str:
    h = hashlib.sha256()
    for name in sorted(t.column_names):
        if name in VOLATILE:
            continue
        h.update(name.encode() + json.dumps(t[name].to_pylist(), default=str).encode())
    return h.hexdigest()[:16]


def _stored(lake, version: str) -> dict:
    return {"document": _digest_json(lake.load_document(version)),
            "zarr": _digest_zarr(lake.open_zarr(version)),
            "residuals": _digest_table(lake.read_residuals(version))}


def _calibrate(folder: Path, lake, settings) -> dict:
    from fieldcal import pipeline

    prepared = pipeline.prepare(folder, settings)
    measurements = {name: pipeline.measure(prepared, name) for name in prepared.to_measure}
    hashes = {name: pipeline.image_hash(prepared, name) for name in prepared.to_measure}
    fp = pipeline.input_fingerprint(prepared, hashes)
    out = pipeline.solve(prepared, measurements, fingerprint_=fp)
    version = lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs)
    return {"solved": _digest_json(out.document), "arrays": _digest_json(
        {k: np.asarray(v).tobytes().hex() for k, v in out.arrays.items() if k not in GRID}), **_stored(lake, version)}


def main() -> int:
    from fieldcal.lake.store import Lake
    from fieldcal.pipeline import Settings
    from fieldcal.rig_run import run_rig
    from fieldcal.synthetic.field import paper_field, wide_field
    from fieldcal.synthetic.goniometer import write_session
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.rig import two_head_rig, write_rig_session
    from fieldcal.synthetic.session_writer import write_field_session

    rows = {}
    with tempfile.TemporaryDirectory(prefix="fieldcal-digest-") as tmp:
        tmp = Path(tmp)
        lake = Lake(tmp / "lake")
        write_field_session(tmp / "obs", wide_field(seed=6), images=False, observations_csv=True, camera_id="cam-obs")
        rows["field observations, targets adjusted"] = _calibrate(tmp / "obs", lake, Settings(targets_adjusted=True))
        images = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]
        write_field_session(tmp / "img", scaled_field(paper_field(), 0.25), image_indices=images, coded=True,
                            seed=4, camera_id="cam-img")
        rows["field images"] = _calibrate(tmp / "img", lake, Settings())
        write_session(tmp / "gonio", "canon5d2", seed=4, raster_scale=0.25, frames_per_angle=1, camera_id="cam-gon")
        rows["goniometer"] = _calibrate(tmp / "gonio", lake, Settings())
        write_rig_session(tmp / "rig", two_head_rig(seed=3))
        rig_version, heads, outcome = run_rig(tmp / "rig", lake)
        rows["rig"] = {"rig document": _digest_json(lake.load_rig_document(rig_version)),
                       **{f"head {i}": "/".join(_stored(lake, v).values()) for i, v in enumerate(heads)}}
    for name, parts in rows.items():
        print(f"{name}: " + " ".join(f"{k}={v}" for k, v in parts.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
