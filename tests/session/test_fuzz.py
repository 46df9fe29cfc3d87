"""Property-based tests (hypothesis) of the session loader and the CSV readers.

Whatever bytes a session folder holds, :func:`fieldcal.pipeline.prepare` and the readers of
targets.csv, observations.csv, marks.csv and frames.csv either return valid data structures
(finite numbers, unique ids, positive sigmas, paths inside the session folder) or raise
:class:`~fieldcal.errors.InputError` with one line naming the file: never another exception,
never a crash. The documents are generated from valid sessions by replacing, deleting and
retyping fields (any JSON value, including NaN and deep nesting) and by corrupting the text;
the tables from valid headers and rows mixed with hostile cells (NaN, inf, 1e999, text,
quotes, embedded newlines, NUL, very long fields, BOMs, raw bytes).

Hypothesis runs derandomised (the ``ci`` profile of ``tests/conftest.py``: every run draws
the same examples, and writes no database into the source tree); ``HYPOTHESIS_PROFILE=explore``
draws new examples, 5000 per test. Every strategy draws from Hypothesis only (no ``random``);
``test_the_strategies_never_use_the_random_module`` checks that in a fresh interpreter,
because in the test session itself Hypothesis cannot tell our draws from another thread's
use of the global ``random`` state (a Dask scheduler or a Prefect client of an earlier test
still running): its "Do not use the `random` module inside strategies" warning then fires
by chance, as an error, and fails a test as ``FlakyFailure`` or ``FlakyStrategyDefinition``
(issue 12). That warning is therefore ignored here and checked there.
"""

import csv
import io
import json
import math
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, currently_in_test_context, event, given, settings
from hypothesis import strategies as st

from fieldcal import pipeline
from fieldcal.contract.names import is_valid, normal_file_name
from fieldcal.errors import InputError
from fieldcal.model.camera import Sensor
from fieldcal.session.data import FieldImage, TargetField
from fieldcal.session.frames import read_frames_csv
from fieldcal.session.loader import read_marks_csv, read_observations_csv, read_targets_csv
from fieldcal.session.tables import read_csv_table

ROOT = Path(__file__).resolve().parents[2]
FUZZ = settings(max_examples=max(200, settings.default.max_examples),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
pytestmark = pytest.mark.filterwarnings(
    "ignore:Do not use the `random` module inside strategies:hypothesis.errors.HypothesisDeprecationWarning")

# --------------------------------------------------------------------------------------
# strategies
# --------------------------------------------------------------------------------------
CHARS = st.characters(blacklist_categories=("Cs",))          # any text that can be UTF-8
HOSTILE_TEXT = ["", " ", "..", "../x", "../../etc/passwd", "/etc/passwd", "C:/x.tif", "\\\\server\\x",
                "images/*.tif", "images/../x.tif", "images/**", "*", "a\x00b", "x" * 300, "t" * 5000,
                "targets.csv", "observations.csv", "frames.csv", "marks.csv", "images", ".",
                "field", "goniometer", "DICT_4X4_1000", "DICT_NOPE", "aruco", "dark", "bright",
                "2026-11-20", "2026-11-20T09:30:00Z", "9999-12-31T23:59:59-23:59", "0001-01-01T00:00+23:59",
                "f_mm", "k1", "b1", "fieldcal.session/1", "cam-1", "\n", "é", "\ufeff", "cam-1\n", "cam\u202e1",
                "g[1]", "images/[ab].tif", "images/./i0.tif", "./images/i0.tif", "images//i1.tif", "S\u2028",
                "c" * 129]
TEXT = st.one_of(st.text(CHARS, max_size=12), st.sampled_from(HOSTILE_TEXT))
LEAF = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70),
                 st.floats(allow_nan=True, allow_infinity=True), TEXT)
JSON_VALUE = st.recursive(LEAF, lambda inner: st.lists(inner, max_size=3)
                          | st.dictionaries(TEXT, inner, max_size=3), max_leaves=8)
DELETE = object()
MANIFEST_KEYS = [
    ("schema",), ("method",), ("camera_id",), ("session_id",), ("acquired",), ("sensor",),
    ("sensor", "width_px"), ("sensor", "height_px"), ("sensor", "pixel_size_um"), ("lens",),
    ("lens", "nominal_focal_mm"), ("field",), ("field", "targets"), ("field", "target_diameter_mm"),
    ("field", "target_polarity"), ("field", "coded"), ("field", "coded", "dictionary"),
    ("field", "coded", "marker_size_mm"), ("frames",), ("images",), ("images", 0),
    ("images", 0, "file"), ("default_sigma_px",), ("estimate",), ("estimate", 0),
]
MUTATION = st.tuples(st.sampled_from(MANIFEST_KEYS), st.one_of(st.just(DELETE), JSON_VALUE,
                                                              st.sampled_from(HOSTILE_TEXT)))
TEXT_DAMAGE = st.one_of(st.none(), st.tuples(st.sampled_from(["truncate", "insert", "replace"]),
                                             st.integers(0, 600), st.text(CHARS, max_size=3)))

CELLS = ["", " ", "0", "-0", "1", "2.5", " 3 ", "1e3", "-7", "1e999", "-1e999", "1e-400", "nan", "NaN",
         "inf", "-Infinity", "0x10", "1_000", "1,5", "abc", "A", "B", "C", "x", "y", "z",
         "images/a.tif", "images/b.tif", "images/c.tif", "../a.tif", '"', '""', "a\nb", "\r", "\x00",
         "images/a\nb.tif", "x\r\ny", "\t", "\x1b[31m",
         "é", "\ufeff", "x" * 200, "A\x00", "\x00", "A\u202e", "a*b", "a/b", "a\\b", "[A]", "\x85", "\u2028",
         "T" * 129, "images/./a.tif", "./images/b.tif", "images//c.tif", "images/*.tif"]
CELL = st.one_of(st.sampled_from(CELLS), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                 st.integers(-10, 10**6).map(str), st.text(CHARS, max_size=6))
HOSTILE = st.one_of(st.sampled_from(CELLS), st.sampled_from(CELLS), CELL)


def note(label: str) -> None:
    """Count outcomes for ``--hypothesis-show-statistics`` (what share of examples is valid)."""
    if currently_in_test_context():
        event(label)


def sometimes(valid, hostile, one_in: int):
    """``valid``, or ``hostile`` once in ``one_in`` draws."""
    return st.integers(0, one_in - 1).flatmap(lambda k: hostile if k == 0 else valid)


NUMBER = st.one_of(st.floats(-1e6, 1e6, allow_nan=False).map(repr), st.integers(-1000, 1000).map(str))
POSITIVE = st.one_of(st.just(""), st.floats(1e-3, 100.0).map(repr))
VALID_CELLS = {
    "id": st.sampled_from(list("ABCDEFGH")), "target_id": st.sampled_from(list("ABCDEF")),
    "X": NUMBER, "Y": NUMBER, "Z": NUMBER, "sigma_mm": POSITIVE, "sigma_px": POSITIVE,
    "code": st.one_of(st.just(""), st.integers(0, 20).map(str)),
    "image": st.sampled_from(["images/a.tif", "images/b.tif", "images/c.tif"]),
    "u": st.floats(-0.5, 99.5).map(repr), "v": st.floats(-0.5, 79.5).map(repr),
    "file": st.sampled_from([f"images/f{k}.tif" for k in range(8)]), "axis": st.sampled_from(["x", "y"]),
    "angle_deg": st.floats(-89.0, 89.0).map(repr),
}


def table_text(columns: list[str]):
    """Bytes of a CSV file: a header (mostly the right one; reordered, cut or arbitrary) and
    rows of valid cells of their column, up to four of them replaced by hostile cells and
    sometimes a row of garbage, written with the csv module or by hand (unbalanced quotes),
    sometimes with a BOM; or (one in 20) raw bytes."""
    header = sometimes(st.one_of(st.just(columns), st.permutations(columns)),
                       st.one_of(st.lists(st.sampled_from(columns + ["", "id", "extra"]), max_size=len(columns) + 1),
                                 st.lists(CELL, max_size=4)), 6)
    row = st.tuples(*(VALID_CELLS[c] for c in columns)).map(list)

    @st.composite
    def build(draw):
        h = draw(header)
        rows = draw(st.lists(row, max_size=6))
        for _ in range(draw(st.integers(0, 4)) if rows else 0):
            k, j = draw(st.integers(0, len(rows) - 1)), draw(st.integers(0, len(columns) - 1))
            rows[k][j] = draw(HOSTILE)
        if draw(st.integers(0, 9)) == 0:
            rows.insert(draw(st.integers(0, len(rows))), draw(st.lists(CELL, max_size=len(columns) + 1)))
        if h != columns and sorted(h) == sorted(columns):  # reordered header: cells follow it
            rows = [[r[columns.index(c)] for c in h] if len(r) == len(columns) else r for r in rows]
        if draw(st.booleans()):
            buf = io.StringIO()
            csv.writer(buf, lineterminator=draw(st.sampled_from(["\n", "\r\n"]))).writerows([h] + rows)
            text = buf.getvalue()
        else:                                     # written by hand: quotes and commas unbalanced
            text = "".join(",".join(line) + "\n" for line in [h] + rows)
        if draw(st.integers(0, 7)) == 0:
            text = "\ufeff" + text
        return text.encode("utf-8")

    return sometimes(build(), st.one_of(st.binary(max_size=120), st.just(b"")), 20)


# --------------------------------------------------------------------------------------
# session folders
# --------------------------------------------------------------------------------------
TARGETS = "id,X,Y,Z,sigma_mm,code\n" + "".join(f"T{k},{k % 4 * 0.5},{k % 3 * -0.2},{k // 4 * 0.5},2,\n"
                                                for k in range(12))
OBSERVATIONS = "image,target_id,u,v,sigma_px\n" + "".join(f"images/i{i}.tif,T{k},{100 + 30 * k},{200 + 9 * i},\n"
                                                          for i in range(3) for k in range(8))
MARKS = "image,target_id,u,v\n" + "".join(f"images/i{i}.tif,T{k},{100 + 30 * k},{200 + 9 * i}\n"
                                          for i in range(3) for k in range(4))
FRAMES = "file,axis,angle_deg\n" + "".join(f"images/{a}{w}.tif,{a},{w}\n" for a in "xy" for w in (-10, 0, 10))
BASES = {
    "observations": {"schema": "fieldcal.session/1", "method": "field", "camera_id": "cam-1",
                     "acquired": "2026-11-20T09:30:00Z",
                     "sensor": {"width_px": 1200, "height_px": 800, "pixel_size_um": 5.0},
                     "lens": {"nominal_focal_mm": 20.0}, "field": {"targets": "targets.csv"},
                     "images": "images/*.tif"},
    "images": {"schema": "fieldcal.session/1", "method": "field", "camera_id": "cam-1",
               "acquired": "2026-11-20", "sensor": {"width_px": 1200, "height_px": 800, "pixel_size_um": 5.0},
               "lens": {"nominal_focal_mm": 20.0},
               "field": {"targets": "targets.csv", "target_polarity": "dark",
                         "coded": {"type": "aruco", "dictionary": "DICT_4X4_1000", "marker_size_mm": 100.0}},
               "images": [{"file": f"images/i{i}.tif", "station": "S1"} for i in range(3)],
               "default_sigma_px": 0.2, "estimate": ["f_mm", "xp_mm", "yp_mm", "k1"]},
    "goniometer": {"schema": "fieldcal.session/1", "method": "goniometer", "camera_id": "cam-2",
                   "acquired": "2026-11-20T09:30:00+01:00",
                   "sensor": {"width_px": 700, "height_px": 460, "pixel_size_um": 50.0},
                   "frames": "frames.csv", "images": "images/*.tif"},
}


def mutate(manifest: dict, path: tuple, value):
    """Set (or delete) ``path`` in a copy-free walk; paths through non-containers are skipped."""
    node = manifest
    for k in path[:-1]:
        if isinstance(node, dict) and k in node:
            node = node[k]
        elif isinstance(node, list) and isinstance(k, int) and k < len(node):
            node = node[k]
        else:
            return
    last = path[-1]
    if isinstance(node, dict):
        if value is DELETE:
            node.pop(last, None)
        else:
            node[last] = value
    elif isinstance(node, list) and isinstance(last, int) and last < len(node):
        if value is DELETE:
            del node[last]
        else:
            node[last] = value


def damage(text: str, how) -> str:
    if how is None:
        return text
    kind, at, chars = how
    at = min(at, len(text))
    if kind == "truncate":
        return text[:at]
    if kind == "insert":
        return text[:at] + chars + text[at:]
    return text[:at] + chars + text[at + len(chars):]


def make_folder(root: Path, base: str, manifest_bytes: bytes) -> Path:
    folder = Path(tempfile.mkdtemp(prefix="s", dir=root))
    (folder / "images").mkdir()
    (folder / "session.json").write_bytes(manifest_bytes)
    (folder / "targets.csv").write_text(TARGETS)
    if base == "observations":
        (folder / "observations.csv").write_text(OBSERVATIONS)
    elif base == "images":
        (folder / "marks.csv").write_text(MARKS)
        for i in range(3):
            (folder / "images" / f"i{i}.tif").write_bytes(b"")
    else:
        (folder / "frames.csv").write_text(FRAMES)
        for a in "xy":
            for w in (-10, 0, 10):
                (folder / "images" / f"{a}{w}.tif").write_bytes(b"")
    return folder


def inside(path: Path, folder: Path) -> bool:
    p, base = Path(path).resolve(), folder.resolve()
    return p == base or base in p.parents


def check_prepared(prepared, folder: Path) -> None:
    """What a successful prepare() promises (CONTRACT section 3)."""
    note("prepared")
    s = prepared.session
    assert s.method in ("field", "goniometer")
    for n in (s.sensor.width_px, s.sensor.height_px):
        assert isinstance(n, int) and 1 <= n <= 200_000
    assert math.isfinite(s.sensor.pixel_size_um) and s.sensor.pixel_size_um > 0
    assert s.nominal_focal_mm is None or (math.isfinite(s.nominal_focal_mm) and s.nominal_focal_mm > 0)
    assert math.isfinite(s.default_sigma_px) and s.default_sigma_px > 0
    assert s.acquired.tzinfo is not None
    assert is_valid(s.camera_id, "id") and is_valid(s.session_id, "id")
    for name in prepared.to_measure:
        assert inside(s.image_path(name), folder)
        assert normal_file_name(name) == name
    for p in (s.targets_path, s.observations_path, s.marks_path, s.frames_path):
        assert p is None or (inside(p, folder) and p.is_file())
    for im in s.images:
        assert inside(folder / im.file, folder)
        assert normal_file_name(im.file) == im.file and (im.station is None or is_valid(im.station, "label"))
    assert len({im.file for im in s.images}) == len(s.images)


def check_refusal(err: InputError, where: str) -> None:
    note("refused")
    text = str(err)
    assert "\n" not in text and "\r" not in text, text
    assert err.where is not None and err.where.startswith(where), text


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


# --------------------------------------------------------------------------------------
# session.json
# --------------------------------------------------------------------------------------
@FUZZ
@given(base=st.sampled_from(sorted(BASES)), mutations=st.lists(MUTATION, max_size=4), how=TEXT_DAMAGE,
       allow_nan=st.booleans())
def test_prepare_of_a_mutated_session_json_succeeds_validly_or_names_the_file(root, base, mutations, how,
                                                                             allow_nan):
    manifest = json.loads(json.dumps(BASES[base]))
    for path, value in mutations:
        mutate(manifest, path, value)
    try:
        text = json.dumps(manifest, allow_nan=allow_nan)
    except ValueError:
        text = json.dumps(manifest, allow_nan=True)
    folder = make_folder(root, base, damage(text, how).encode("utf-8"))
    try:
        prepared = pipeline.prepare(folder)
    except InputError as err:
        check_refusal(err, str(folder))
    else:
        check_prepared(prepared, folder)


@FUZZ
@given(base=st.sampled_from(sorted(BASES)), raw=st.one_of(st.binary(max_size=200), st.text(CHARS, max_size=200)
                                                        .map(lambda t: t.encode("utf-8"))))
def test_prepare_of_arbitrary_bytes_as_session_json_names_the_file(root, base, raw):
    folder = make_folder(root, base, raw)
    with pytest.raises(InputError) as info:
        pipeline.prepare(folder)
    check_refusal(info.value, str(folder / "session.json"))


def test_the_fuzzed_bases_are_valid_sessions(root):
    """The generated documents start from sessions that load (else every example would be a refusal)."""
    for base, manifest in BASES.items():
        folder = make_folder(root, base, json.dumps(manifest).encode())
        prepared = pipeline.prepare(folder)
        check_prepared(prepared, folder)
        assert prepared.method == ("goniometer" if base == "goniometer" else "field")


# --------------------------------------------------------------------------------------
# the CSV readers
# --------------------------------------------------------------------------------------
REF_TARGETS = TargetField(np.array(list("ABCDEF")), np.zeros((6, 3)), 5.0, -1)
SENSOR = Sensor(100, 80, 5.0)


def _write(root: Path, name: str, data: bytes) -> Path:
    p = Path(tempfile.mkdtemp(prefix="t", dir=root)) / name
    p.write_bytes(data)
    return p


@FUZZ
@given(data=table_text(["id", "X", "Y", "Z", "sigma_mm", "code"]))
def test_targets_csv_reads_validly_or_names_the_file(root, data):
    p = _write(root, "targets.csv", data)
    try:
        t = read_targets_csv(p)
    except InputError as err:
        check_refusal(err, str(p))
        return
    note("read")
    n = len(t)
    assert n >= 1 and len(set(t.ids.tolist())) == n and all(is_valid(i, "label") for i in t.ids.tolist())
    # a surveyed target: X, Y, Z finite; an unsurveyed one: all three NaN (CONTRACT section 3)
    assert t.xyz_m.shape == (n, 3) and (np.isfinite(t.xyz_m).all(axis=1) | np.isnan(t.xyz_m).all(axis=1)).all()
    assert np.isfinite(t.sigma_mm).all() and (t.sigma_mm > 0).all()
    codes = t.codes[t.codes >= 0]
    assert (t.codes >= -1).all() and len(np.unique(codes)) == len(codes)


@FUZZ
@given(data=table_text(["image", "target_id", "u", "v", "sigma_px"]), allow_new=st.booleans(),
       with_sensor=st.booleans())
def test_observations_csv_reads_validly_or_names_the_file(root, data, allow_new, with_sensor):
    p = _write(root, "observations.csv", data)
    images = [FieldImage("images/a.tif"), FieldImage("images/b.tif")]
    try:
        obs = read_observations_csv(p, REF_TARGETS, images, default_sigma_px=0.1, allow_new_images=allow_new,
                                    sensor=SENSOR if with_sensor else None)
    except InputError as err:
        check_refusal(err, str(p))
        return
    note("read")
    m = len(obs)
    assert m >= 1 and obs.uv_px.shape == (m, 2) and np.isfinite(obs.uv_px).all()
    assert np.isfinite(obs.sigma_px).all() and (obs.sigma_px > 0).all()
    assert ((0 <= obs.target) & (obs.target < 6)).all() and ((0 <= obs.image) & (obs.image < len(images))).all()
    assert len(images) == 2 or allow_new
    assert all(normal_file_name(im.file) == im.file for im in images) and len({im.file for im in images}) == len(images)
    assert len({(i, t) for i, t in zip(obs.image.tolist(), obs.target.tolist(), strict=True)}) == m
    if with_sensor:
        assert (obs.uv_px >= -0.5).all() and (obs.uv_px[:, 0] <= 99.5).all() and (obs.uv_px[:, 1] <= 79.5).all()


@FUZZ
@given(data=table_text(["image", "target_id", "u", "v"]))
def test_marks_csv_reads_validly_or_names_the_file(root, data):
    p = _write(root, "marks.csv", data)
    images = [FieldImage("images/a.tif"), FieldImage("images/b.tif")]
    try:
        marks = read_marks_csv(p, REF_TARGETS, images)
    except InputError as err:
        check_refusal(err, str(p))
        return
    note("read")
    assert marks and set(marks) <= {0, 1} and len(images) == 2
    for t, uv in marks.values():
        assert len(np.unique(t)) == len(t) and ((0 <= t) & (t < 6)).all()
        assert uv.shape == (len(t), 2) and np.isfinite(uv).all()


@FUZZ
@given(data=table_text(["file", "axis", "angle_deg"]), strict=st.booleans())
def test_frames_csv_reads_validly_or_names_the_file(root, data, strict):
    p = _write(root, "frames.csv", data)
    try:
        t = read_frames_csv(p, strict=strict)
    except InputError as err:
        check_refusal(err, str(p))
        return
    note("read")
    assert t.column_names == ["file", "axis", "angle_deg", "line", "problem"] and t.num_rows >= 1
    files = t["file"].to_pylist()
    assert len(set(f for f in files if f)) == len([f for f in files if f])     # no file listed twice
    for f, a, w, line, problem in zip(*(t[c].to_pylist() for c in t.column_names), strict=True):
        assert line >= 2
        if problem is None:
            assert f and a in ("x", "y") and math.isfinite(w) and abs(w) < 90.0
        else:
            assert not strict and problem.startswith(f"frames.csv line {line}: ") and "\n" not in problem


# --------------------------------------------------------------------------------------
# the two tokenisers, and the strategies themselves
# --------------------------------------------------------------------------------------
TABLES = {"targets.csv": (("id", "X", "Y", "Z"), ("sigma_mm", "code")),
          "observations.csv": (("image", "target_id", "u", "v"), ("sigma_px",))}


def _tokenised(p: Path, kind: str, tokeniser: str):
    required, optional = TABLES[kind]
    try:
        t = read_csv_table(p, required, optional, kind=kind, tokeniser=tokeniser)
    except InputError as err:
        return "refused", err.reason
    return "read", t.header, {k: v.to_pylist() for k, v in t.columns.items()}, t.lines.tolist()


@FUZZ
@given(kind=st.sampled_from(sorted(TABLES)), data=st.one_of(
    table_text(["id", "X", "Y", "Z", "sigma_mm", "code"]), table_text(["image", "target_id", "u", "v", "sigma_px"])))
def test_pyarrow_and_python_split_a_file_without_quotes_alike(root, kind, data):
    """The fast tokeniser (pyarrow, quote-free files) gives the same header, cells, line numbers
    and refusals as Python's csv module, or declines the file (then Python reads it)."""
    p = _write(root, kind, data.replace(b'"', b""))
    arrow = _tokenised(p, kind, "arrow")
    if arrow[0] == "refused" and arrow[1].startswith("pyarrow cannot split"):
        note("pyarrow declined")
        return
    note(f"pyarrow {arrow[0]}")
    assert arrow == _tokenised(p, kind, "python")


def test_the_strategies_never_use_the_random_module():
    """Draw from every strategy of this module in a fresh interpreter (no other thread touches
    ``random`` there) with Hypothesis's warning as an error (see the module docstring)."""
    code = textwrap.dedent("""
        import warnings
        warnings.simplefilter("error")
        from hypothesis import HealthCheck, given, settings, strategies as st
        import tests.session.test_fuzz as f
        columns = [["id", "X", "Y", "Z", "sigma_mm", "code"], ["image", "target_id", "u", "v", "sigma_px"],
                   ["image", "target_id", "u", "v"], ["file", "axis", "angle_deg"]]
        strategies = [st.lists(f.MUTATION, max_size=4), f.TEXT_DAMAGE, f.JSON_VALUE, f.HOSTILE,
                      *(f.table_text(c) for c in columns)]
        for s in strategies:
            @settings(derandomize=True, database=None, max_examples=20, deadline=None,
                      suppress_health_check=list(HealthCheck))
            @given(s)
            def draw(x):
                pass
            draw()
        print("ok", len(strategies))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["ok", "8"]
