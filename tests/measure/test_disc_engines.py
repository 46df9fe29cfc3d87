"""One contract for both engines of the disc detector's window stage.

``engine="numpy"`` (:mod:`fieldcal.measure.disc_windows`, the reference) and
``engine="numba"`` (:mod:`fieldcal.measure.disc_kernel`, compiled per window) must give
the same detections, the same flags and filter verdicts, and centres equal within
``CENTRE_TOL_PX``; each must also meet the truth of the made-up scenes on its own. The
compiled kernel is loaded ahead of the first image (``warm_up``, Numba's cache), and
without Numba (or when it cannot compile) the detector runs on the reference with one
logged line saying why.
"""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pytest
from scipy import ndimage

from fieldcal.errors import InputError
from fieldcal.measure import disc_kernel, disc_windows
from fieldcal.measure.discs import ENGINES, METHODS, default_engine, detect_targets
from tests.measure.test_targets import grid_centres, match, render_discs, rms

ROOT = Path(__file__).resolve().parents[2]

CENTRE_TOL_PX = 1e-4
"""Centres of the two engines agree to this [px]: the kernel fits the conic in float64 where
the reference sums in float32 (measured differences ~2e-6 px), 50 x below the 0.005 px
noise floor of the best-exposed tests."""
SIZE_TOL_PX = 1e-4        # diameters and axes [px], same reason
REL_TOL = 1e-9            # contrast, noise, SNR: the same float64 sums in another order
ANGLE_TOL_DEG = 0.01      # major-axis angle of ellipses with roundness < 0.9 (undefined for circles)

needs_kernel = pytest.mark.skipif(not disc_kernel.available(),
                                  reason=f"the compiled kernel is not available: {disc_kernel.problem()}")


@pytest.fixture(params=[pytest.param(e, marks=needs_kernel if e == "numba" else ()) for e in ENGINES])
def engine(request):
    return request.param


# --------------------------------------------------------------------------------------
# scenes: (name, image, truth centres, keyword arguments)
# --------------------------------------------------------------------------------------
def _scenes():
    rng = np.random.default_rng(21)
    out = []
    c = grid_centres(6, 46.0, 28.0, rng)
    out.append(("dark grid, SNR ~160", render_discs((290, 290), c, rng.uniform(9.0, 13.0, len(c)),
                                                    noise_dn=220.0, seed=1), c, {}))
    c = grid_centres(4, 60.0, 35.0, rng)
    out.append(("oblique ellipses", render_discs((250, 250), c, 15.0, minor=6.0,
                                                 angles=rng.uniform(0, 180, len(c)), noise_dn=150.0,
                                                 seed=2), c, {}))
    c = grid_centres(3, 50.0, 30.0, rng)
    out.append(("bright discs", render_discs((160, 160), c, 10.0, bg=3000.0, fig=30000.0, noise_dn=150.0,
                                             seed=3), c, {"polarity": "bright"}))
    c = np.array([(4.0, 40.0), (60.0, 2.5), (95.0, 60.0), (40.3, 40.6), (75.7, 30.2)])
    out.append(("cut by the border", render_discs((100, 100), c, 9.0, noise_dn=150.0, seed=4), c, {}))
    c = np.array([(30.3, 30.1), (90.6, 30.4)])
    sat = render_discs((120, 120), c, 10.0, bg=2000.0, fig=90000.0, noise_dn=100.0, seed=5)
    out.append(("saturated bright discs", sat, c, {"polarity": "bright"}))
    c = grid_centres(5, 20.0, 16.0, rng)                        # neighbours reach into the rings
    out.append(("crowded, low SNR", render_discs((112, 112), c, 7.0, noise_dn=2500.0, seed=6), c,
                {"min_diameter_px": 8}))
    img = render_discs((200, 260), [(60.3, 60.7), (180.2, 120.6)], 11.0, noise_dn=0.0).astype(float)
    vv, uu = np.mgrid[:200, :260]
    clutter = np.zeros((200, 260))
    clutter[(np.abs(uu - 0.4 * vv - 100) < 1.5)] = 1.0
    clutter[150:156, 10:200] = 1.0
    clutter[20:44, 150:174] = 1.0
    clutter = ndimage.gaussian_filter(clutter, 0.8)
    img = np.clip(np.rint(img - 36000.0 * clutter + rng.normal(0, 300.0, img.shape)), 0, 65535)
    out.append(("clutter", img.astype(np.uint16), np.array([(60.3, 60.7), (180.2, 120.6)]), {}))
    c = grid_centres(3, 40.0, 25.0, rng)
    out.append(("8-bit", (render_discs((110, 110), c, 9.0, noise_dn=150.0, seed=7) >> 8).astype(np.uint8), c, {}))
    return out


SCENES = _scenes()


def _column(t, name):
    return np.asarray(t[name].to_numpy(zero_copy_only=False))


# --------------------------------------------------------------------------------------
# the contract: both engines give the same table
# --------------------------------------------------------------------------------------
@needs_kernel
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scene", SCENES, ids=[s[0] for s in SCENES])
def test_both_engines_give_the_same_detections_flags_and_centres(scene, method):
    _, img, _, kw = scene
    ref = detect_targets(img, method=method, return_rejected=True, engine="numpy", **kw)
    ker = detect_targets(img, method=method, return_rejected=True, engine="numba", **kw)
    assert ref.num_rows == ker.num_rows
    assert ker["reject"].to_pylist() == ref["reject"].to_pylist()           # same filter verdicts
    for flag in ("saturated", "truncated"):
        assert _column(ker, flag).tolist() == _column(ref, flag).tolist()
    for name, tol in (("u_px", CENTRE_TOL_PX), ("v_px", CENTRE_TOL_PX), ("diameter_px", SIZE_TOL_PX),
                      ("major_px", SIZE_TOL_PX), ("minor_px", SIZE_TOL_PX), ("edge_rms_px", SIZE_TOL_PX)):
        a, b = _column(ref, name).astype(float), _column(ker, name).astype(float)
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        assert np.nanmax(np.abs(a - b), initial=0.0) <= tol, name
    for name in ("contrast", "snr"):
        assert np.allclose(_column(ker, name), _column(ref, name), rtol=REL_TOL, atol=0.0), name
    # the a-priori sigma goes with 1 / sqrt(diameter): relative 1e-6 from the diameters' 1e-4 px
    assert np.allclose(_column(ker, "sigma_px"), _column(ref, "sigma_px"), rtol=1e-6, atol=0.0)
    oblique = _column(ref, "roundness") < 0.9
    d_angle = (_column(ker, "angle_deg") - _column(ref, "angle_deg") + 90.0) % 180.0 - 90.0
    assert np.all(np.abs(d_angle[oblique]) <= ANGLE_TOL_DEG)


def _random_windows(rng, img, n, sizes=(8, 12, 20, 32, 44)):
    H, W = img.shape
    S = rng.choice(sizes, n)
    y0 = np.array([rng.integers(0, H - s + 1) for s in S])
    x0 = np.array([rng.integers(0, W - s + 1) for s in S])
    y0[:4], x0[:4] = 0, 0                                        # windows at the image's corners
    y0[4:8], x0[4:8] = H - S[4:8], W - S[4:8]
    return y0, x0, rng.uniform(0, S - 1), rng.uniform(0, S - 1), S


@needs_kernel
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("sign", [-1, 1])
def test_window_stage_agrees_on_arbitrary_windows(method, sign):
    # windows anywhere: on discs, on their edges, on noise, cut by the image border, small;
    # seeds that are not beyond the threshold (empty regions), fits that fail
    rng = np.random.default_rng(22 + sign)
    c = grid_centres(6, 30.0, 20.0, rng)
    img = render_discs((200, 200), c, rng.uniform(4.0, 9.0, len(c)), noise_dn=1500.0, seed=8,
                       bg=20000.0 if sign < 0 else 4000.0, fig=4000.0 if sign < 0 else 30000.0)
    y0, x0, su, sv, S = _random_windows(rng, img, 300)
    kw = dict(sign=sign, step=3, method=method, upsample=4, sat_level=65535, noise_dn=1500.0)
    ref = disc_windows.measure_windows(img, y0, x0, su, sv, S, **kw)
    ker = disc_kernel.measure_windows(img, y0, x0, su, sv, S, **kw)
    for k in ("truncated", "overflow", "saturated", "fit_ok", "area", "n_edge"):
        assert np.array_equal(ker[k], ref[k]), k
    assert ref["fit_ok"].sum() > 100 and (~ref["fit_ok"]).sum() > 10      # both kinds are covered
    for k in ("noise", "contrast", "threshold"):
        assert np.allclose(ker[k], ref[k], rtol=REL_TOL, atol=1e-9), k
    ok = ref["fit_ok"]
    # a disc's outline (many edge points all round, not a sliver): the contract's tolerance
    outline = ok & (ref["n_edge"] >= 24) & (ref["eb"] >= 0.5 * ref["ea"])
    assert outline.sum() > 100
    for k in ("eu", "ev", "cu", "cv", "ea", "eb"):
        assert np.max(np.abs(ker[k][outline] - ref[k][outline])) <= CENTRE_TOL_PX, k
        # any other fit: a few points on a partial outline or a sliver, which the filters
        # refuse; the reference's float32 normal equations are ill-conditioned there
        assert np.max(np.abs(ker[k][ok] - ref[k][ok])) <= 0.01, k
    assert np.isnan(ker["eu"][~ok]).all()
    # `tight` compares the fitted outline with the ring: equal except within the fit's
    # round-off of the boundary (none in this set)
    assert np.array_equal(ker["tight"], ref["tight"])


# --------------------------------------------------------------------------------------
# each engine on its own meets the truth
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
def test_each_engine_finds_every_disc_accurately(engine, method):
    _, img, truth, kw = SCENES[0]
    t = detect_targets(img, method=method, engine=engine, **kw)
    j, uv = match(t, truth)
    assert (j >= 0).all() and t.num_rows == len(truth)
    assert rms(uv[j] - truth) < 0.01                             # SNR ~160: ~0.005 px reached


def test_each_engine_flags_the_border_and_the_saturation(engine):
    _, img, truth, kw = SCENES[3]
    t = detect_targets(img, engine=engine, **kw)
    j, _ = match(t, truth, radius=4.0)
    trunc = _column(t, "truncated")
    assert (j[3:] >= 0).all() and not trunc[j[3:]].any() and trunc[j[:3][j[:3] >= 0]].all()
    _, img, truth, kw = SCENES[4]
    t = detect_targets(img, engine=engine, **kw)
    assert _column(t, "saturated")[match(t, truth)[0]].all()


def test_each_engine_rejects_the_clutter(engine):
    _, img, truth, kw = SCENES[6]
    t = detect_targets(img, engine=engine, return_rejected=True, **kw)
    acc = t.filter(pc.equal(t["reject"], ""))
    assert acc.num_rows == len(truth) and (match(acc, truth)[0] >= 0).all()
    assert t.num_rows > acc.num_rows                             # the clutter was seen, and refused


# --------------------------------------------------------------------------------------
# compiled ahead of the first image; the fallback
# --------------------------------------------------------------------------------------
def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)


@needs_kernel
def test_warm_up_loads_the_compiled_kernels_from_the_cache():
    # the first process may compile and write the cache; a second one only loads it
    code = """
        import json
        from fieldcal.measure import disc_kernel as k
        assert k.warm_up()
        sigs = [str(s) for s in k._measure_all.signatures]
        print(json.dumps({"sigs": sigs, "misses": dict(k._measure_all.stats.cache_misses)}))
    """
    first = _python(code)
    assert first.returncode == 0, first.stderr
    second = _python(code)
    assert second.returncode == 0, second.stderr
    out = json.loads(second.stdout.strip().splitlines()[-1])
    assert any("uint8" in s for s in out["sigs"]) and any("uint16" in s for s in out["sigs"])
    assert sum("'C', True" in s.split("),")[0] for s in out["sigs"]) == 2     # read-only uint8, uint16
    assert out["misses"] == {}                                   # loaded, not compiled


@needs_kernel
def test_after_the_warm_up_measuring_real_files_loads_or_compiles_nothing_more(tmp_path):
    # every layout: an uncompressed TIFF is measured in place (a read-only view, another
    # specialisation of the kernel than a decoded image)
    code = f"""
        import json
        import tifffile
        from fieldcal.measure import disc_kernel as k
        from fieldcal.measure.imageio import read_file
        from fieldcal.measure.targets import measure_image
        from fieldcal.measure.warm import warm_up_measuring
        from tests.measure.test_targets import render_discs
        assert warm_up_measuring()
        kernels = [k._measure_all, k._component_sums]
        before = [sorted(map(str, d.signatures)) for d in kernels]
        img = render_discs((240, 320), [(80.3, 90.6), (200.2, 150.4)], 14.0)
        found = []
        for i, kw in enumerate([dict(compression="zstd", tile=(64, 64)), dict(rowsperstrip=16),
                                dict(compression="adobe_deflate", tile=(64, 64), bigtiff=True)]):
            path = {str(tmp_path)!r} + f"/img{{i}}.tif"
            tifffile.imwrite(path, img, photometric="minisblack", metadata=None, **kw)
            found.append(measure_image(read_file(path)).num_rows)
        after = [sorted(map(str, d.signatures)) for d in kernels]
        print(json.dumps({{"same": before == after, "found": found, "before": before}}))
    """
    assert _python(code).returncode == 0                        # the first process may compile
    out = _python(code)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["found"] == [2, 2, 2]
    assert got["same"], got["before"]
    assert any("Array(uint16, 2, 'C', True" in s for s in got["before"][0])   # read-only


def test_without_numba_the_reference_runs_and_one_line_says_why():
    out = _python("""
        import sys
        sys.modules["numba"] = None                              # `import numba` fails
        from tests.measure.test_targets import render_discs
        from fieldcal.measure.discs import default_engine, detect_targets
        t = detect_targets(render_discs((60, 60), [(30.2, 29.7)], 9.0))
        t2 = detect_targets(render_discs((60, 60), [(30.2, 29.7)], 9.0))
        print(default_engine(), t.num_rows, t2.num_rows, round(t["u_px"][0].as_py(), 1))
        try:
            detect_targets(render_discs((60, 60), [(30.2, 29.7)], 9.0), engine="numba")
        except Exception as err:
            print(type(err).__name__, err)
    """)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines[0] == "numpy 1 1 30.2"
    assert lines[1].startswith("InputError engine 'numba' is not available here: numba cannot be imported")
    logged = out.stderr.strip().splitlines()
    assert len(logged) == 1                                      # one line, once per process
    assert "numba cannot be imported" in logged[0] and "NumPy reference" in logged[0]


def test_when_the_kernel_cannot_compile_the_reference_runs_and_one_line_says_why():
    out = _python("""
        import numba
        from numba.core.errors import LoweringError

        def njit(*args, **kwargs):                               # a platform where lowering fails
            def wrap(fn):
                def fail(*a, **k):
                    raise LoweringError("no code for this target (simulated)")
                return fail
            return wrap

        numba.njit = njit
        from tests.measure.test_targets import render_discs
        from fieldcal.measure import disc_kernel
        from fieldcal.measure.discs import default_engine, detect_targets
        t = detect_targets(render_discs((60, 60), [(30.2, 29.7)], 9.0))
        print(disc_kernel.available(), default_engine(), t.num_rows)
    """)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False numpy 1"
    logged = out.stderr.strip().splitlines()
    assert len(logged) == 1
    assert "cannot be compiled (LoweringError: no code for this target (simulated))" in logged[0]


@needs_kernel
def test_the_default_engine_is_the_compiled_one_here():
    assert default_engine() == "numba"
    with pytest.raises(InputError, match="engine must be one of 'numba', 'numpy'"):
        detect_targets(np.zeros((20, 20), np.uint16), engine="cython")


@needs_kernel
def test_region_growing_is_the_8_connected_component_of_the_seed():
    # the kernel's two ways of growing the region (one blob row by row, or the span fill)
    # against SciPy's labelling, on blobs with noise, neighbours, holes and U shapes
    rng = np.random.default_rng(23)
    simple = 0
    for trial in range(400):
        S = int(rng.integers(6, 48))
        yy, xx = np.mgrid[:S, :S]
        m = ((yy - rng.uniform(0, S)) ** 2 + (xx - rng.uniform(0, S)) ** 2) < rng.uniform(4, S) ** 2
        if trial % 2:
            m ^= rng.random((S, S)) < rng.uniform(0.0, 0.3)      # noise, holes, bridges
        if trial % 5 == 0:
            m = (np.abs(yy - S / 2) + np.abs(xx - S / 2) < S / 2) & ~((yy < S / 2) & (np.abs(xx - S / 2) < S / 6))
        m = m.astype(np.uint8)
        sy, sx = int(rng.integers(S)), int(rng.integers(S))
        lab, _ = ndimage.label(m, structure=np.ones((3, 3)))
        ref = (lab == lab[sy, sx]) & (m == 1)
        L, R, T, B = (np.empty(S, np.int64) for _ in range(4))
        mask = m.ravel().copy()
        whole = disc_kernel._grow_simple(mask, S, sy, sx, m.sum(axis=1).astype(np.int64), L, R, T, B)
        if whole:
            simple += 1
            got = m == 1
        else:
            disc_kernel._grow_region(mask, S, sy, sx, np.empty((S * S, 4), np.int64), L, R, T, B)
            got = mask.reshape(S, S) == 2
        assert np.array_equal(got, ref), trial
        rows, cols = np.flatnonzero(ref.any(1)), np.flatnonzero(ref.any(0))
        assert (R[np.setdiff1d(np.arange(S), rows)] == -1).all()
        for i in rows:
            assert (L[i], R[i]) == (np.flatnonzero(ref[i])[0], np.flatnonzero(ref[i])[-1])
        for j in cols:
            assert (T[j], B[j]) == (np.flatnonzero(ref[:, j])[0], np.flatnonzero(ref[:, j])[-1])
    assert 50 < simple < 350                                     # both ways were exercised
