"""Bad session folders, as the flow meets them: ``pipeline.prepare`` (what ``fieldcal run`` and
the calibration flow call first), and ``fieldcal run`` itself.

Every refusal is an :class:`~fieldcal.errors.InputError` of one line that starts with the
file (and row, or the JSON pointer of the bad field) and says what is wrong: session.json
that is not JSON or violates the schema, paths that leave the session folder (``..``,
absolute, drive letters, links out, NUL characters, names the OS refuses), and the four
tables (targets.csv, observations.csv, marks.csv, frames.csv) with missing columns,
duplicate ids, NaN / infinite / non-numeric values, empty files. ``tests/test_session.py``
covers the readers one by one; this file covers what it does not, at the level a user
meets it. The last tests run ``fieldcal run`` as a subprocess: exit status 2 for bad
input and 1 for geometry that cannot calibrate, one line on stderr, and nothing in the lake.
"""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import tests.conftest as _conftest
from fieldcal import pipeline
from fieldcal.errors import InputError
from fieldcal.lake.store import Lake
from tests.field.test_bad_geometry import CONVERGENT, SAME_DIRECTION, wall, write_obs_session

if not hasattr(_conftest, "prefect_server"):   # until tests/conftest.py provides it
    from tests.conftest_prefect import prefect_server  # noqa: F401

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))


# --------------------------------------------------------------------------------------
# three small valid sessions to break: observation-only, images with marks, goniometer
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def templates(tmp_path_factory):
    root = tmp_path_factory.mktemp("templates")
    obs = write_obs_session(root / "obs", wall(relief_m=1.0), CONVERGENT)

    marks = root / "marks"
    shutil.copytree(obs, marks)
    rows = (marks / "observations.csv").read_text().splitlines()[1:]
    (marks / "observations.csv").unlink()
    per_image: dict[str, list[str]] = {}
    for r in rows:
        per_image.setdefault(r.split(",")[0], []).append(r)
    (marks / "images").mkdir()
    for name in per_image:
        (marks / name).write_bytes(b"")            # prepare lists images, it does not read them
    (marks / "marks.csv").write_text("image,target_id,u,v\n" + "".join(
        ",".join(r.split(",")[:4]) + "\n" for rs in per_image.values() for r in rs[::9][:5]))
    manifest = json.loads((marks / "session.json").read_text())
    manifest["images"] = [{"file": name, "station": f"S{i}"} for i, name in enumerate(per_image)]
    (marks / "session.json").write_text(json.dumps(manifest))

    gonio = root / "gonio"
    (gonio / "images").mkdir(parents=True)
    frames = [(f"images/{a}{w:+d}.tif", a, w) for a in "xy" for w in (-20, -10, 0, 10, 20)]
    for f, _, _ in frames:
        (gonio / f).write_bytes(b"")
    (gonio / "frames.csv").write_text("file,axis,angle_deg\n" + "".join(f"{f},{a},{w}\n" for f, a, w in frames))
    (gonio / "session.json").write_text(json.dumps({
        "schema": "fieldcal.session/1", "method": "goniometer", "camera_id": "cam-lab",
        "acquired": "2026-11-20", "sensor": {"width_px": 702, "height_px": 468, "pixel_size_um": 51.2},
        "lens": {"nominal_focal_mm": 50.0}, "frames": "frames.csv", "images": "images/*.tif"}))
    for folder in (obs, marks, gonio):             # the templates are valid
        pipeline.prepare(folder)
    return {"obs": obs, "marks": marks, "gonio": gonio}


def copy(templates, kind, dest: Path) -> Path:
    shutil.copytree(templates[kind], dest, symlinks=True)
    return dest


def patch_manifest(folder: Path, change) -> None:
    m = json.loads((folder / "session.json").read_text())
    change(m)
    (folder / "session.json").write_text(json.dumps(m))


def refused(folder, match, file="session.json"):
    """prepare(folder) raises InputError: one line, starting with the file, matching ``match``."""
    with pytest.raises(InputError, match=match) as info:
        pipeline.prepare(folder)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(str(Path(folder) / file)), text
    return text


# --------------------------------------------------------------------------------------
# session.json: not JSON
# --------------------------------------------------------------------------------------
def _good(folder):
    return (folder / "session.json").read_text()


NOT_JSON = [
    ("empty", lambda t: b"", r"invalid JSON: Expecting value at line 1 column 1"),
    ("blank", lambda t: b" \n\t\n", r"invalid JSON: Expecting value at line 3 column 1"),
    ("truncated", lambda t: t[: len(t) // 2].encode(), r"invalid JSON: .* at line 1 column \d+"),
    ("array", lambda t: b"[1, 2, 3]", r"must be a JSON object"),
    ("nan", lambda t: t.replace('"pixel_size_um": 7.8', '"pixel_size_um": NaN').encode(),
     r"invalid JSON: NaN is not a JSON number"),
    ("infinity", lambda t: t.replace('"nominal_focal_mm": 24.0', '"nominal_focal_mm": Infinity').encode(),
     r"invalid JSON: Infinity is not a JSON number"),
    ("duplicate_key", lambda t: t.replace('"method": "field"', '"method": "field", "method": "goniometer"').encode(),
     r"invalid JSON: duplicate key\(s\) \['method'\] in an object"),
    ("deep", lambda t: b"[" * 100_000 + b"]" * 100_000, r"invalid JSON: maximum recursion depth"),
    ("huge_number", lambda t: t.replace('"width_px": 3000', '"width_px": 1' + "0" * 5000).encode(),
     r"invalid JSON: Exceeds the limit \(4300 digits\)"),
    ("latin1", lambda t: t.replace("cam-geometry", "cam-g\xe9om").encode("latin-1"), r"not UTF-8 text"),
    ("utf16", lambda t: t.encode("utf-16"), r"not UTF-8 text"),
]


@pytest.mark.parametrize("make, match", [c[1:] for c in NOT_JSON], ids=[c[0] for c in NOT_JSON])
def test_manifest_that_is_not_json_is_refused_in_one_line(templates, tmp_path, make, match):
    folder = copy(templates, "obs", tmp_path / "s")
    (folder / "session.json").write_bytes(make(_good(folder)))
    refused(folder, match)


def test_manifest_with_a_utf8_byte_order_mark_is_read(templates, tmp_path):
    folder = copy(templates, "obs", tmp_path / "s")
    (folder / "session.json").write_bytes(b"\xef\xbb\xbf" + _good(folder).encode())
    assert pipeline.prepare(folder).session.camera_id == "cam-geometry"


# --------------------------------------------------------------------------------------
# session.json: schema violations name the JSON pointer of the bad field
# --------------------------------------------------------------------------------------
def _set(path, value):
    def change(m):
        *head, last = path
        for k in head:
            m = m.setdefault(k, {})
        if value is KeyError:
            del m[last]
        else:
            m[last] = value
    return change


SCHEMA = [
    ("no_pixel_size", ("obs", ("sensor", "pixel_size_um"), KeyError),
     r"'pixel_size_um' is a required property \(at /sensor\)"),
    ("zero_height", ("obs", ("sensor", "height_px"), 0), r"0 is less than the minimum of 1 \(at /sensor/height_px\)"),
    ("width_as_text", ("obs", ("sensor", "width_px"), "3000"),
     r"'3000' is not of type 'integer' \(at /sensor/width_px\)"),
    ("width_as_bool", ("obs", ("sensor", "width_px"), True), r"True is not of type 'integer' \(at /sensor/width_px\)"),
    ("negative_focal", ("obs", ("lens", "nominal_focal_mm"), -24.0), r"\(at /lens/nominal_focal_mm\)"),
    ("zero_sigma", ("obs", ("default_sigma_px",), 0), r"\(at /default_sigma_px\)"),
    ("polarity", ("obs", ("field", "target_polarity"), "grey"),
     r"'grey' is not one of \['dark', 'bright'\] \(at /field/target_polarity\)"),
    ("no_targets", ("obs", ("field", "targets"), KeyError), r"'targets' is a required property \(at /field\)"),
    ("coded_size", ("obs", ("field", "coded"), {"type": "aruco", "dictionary": "DICT_4X4_1000"}),
     r"'marker_size_mm' is a required property \(at /field/coded\)"),
    ("coded_dictionary", ("obs", ("field", "coded"), {"type": "aruco", "dictionary": "DICT_9X9_7",
                                                      "marker_size_mm": 100}),
     r"unknown ArUco dictionary 'DICT_9X9_7' .*\(at /field/coded/dictionary\)"),
    ("normal_short", ("obs", ("field", "target_normal"), [0.0, -1.0]), r"is too short \(at /field/target_normal\)"),
    ("normal_text", ("obs", ("field", "target_normal"), [0.0, "-1", 0.0]),
     r"'-1' is not of type 'number' \(at /field/target_normal/1\)"),
    ("normal_not_unit", ("obs", ("field", "target_normal"), [0.0, -2.0, 0.0]),
     r"field\.target_normal must be a unit vector, got \[0\.0, -2\.0, 0\.0\] of length 2 \(at /field/target_normal\)"),
    ("normal_zero", ("obs", ("field", "target_normal"), [0, 0, 0]),
     r"field\.target_normal must be a unit vector, got \[0\.0, 0\.0, 0\.0\] of length 0"),
    ("estimate_unknown", ("obs", ("estimate",), ["f_mm", "zoom"]), r"'zoom' is not one of .* \(at /estimate/1\)"),
    ("estimate_twice", ("obs", ("estimate",), ["f_mm", "f_mm"]), r"has non-unique elements \(at /estimate\)"),
    ("session_id", ("obs", ("session_id",), "../elsewhere"), r"\(at /session_id\)"),
    ("acquired_number", ("obs", ("acquired",), 20261120), r"20261120 is not of type 'string' \(at /acquired\)"),
    ("acquired_overflow", ("obs", ("acquired",), "9999-12-31T23:59:59-23:59"),
     r"'acquired' is out of range in UTC: .* \(at /acquired\)"),
    ("images_number", ("obs", ("images",), 5), r"\(at /images\)"),
    ("frames_in_field", ("obs", ("frames",), "frames.csv"), r"should not be valid under .* \(at /\)"),
    ("gonio_field", ("gonio", ("field",), {"targets": "t.csv"}), r"should not be valid under .* \(at /\)"),
    ("gonio_no_frames", ("gonio", ("frames",), KeyError), r"'frames' is a required property \(at /\)"),
    ("gonio_estimate", ("gonio", ("estimate",), ["f_mm", "a1"]),
     r"estimate names \['a1'\], not estimable by the goniometer"),
]


@pytest.mark.parametrize("kind, path, value, match", [(k, p, v, m) for _, (k, p, v), m in SCHEMA],
                         ids=[c[0] for c in SCHEMA])
def test_schema_violations_name_the_json_pointer(templates, tmp_path, kind, path, value, match):
    folder = copy(templates, kind, tmp_path / "s")
    patch_manifest(folder, _set(path, value))
    refused(folder, match)


# --------------------------------------------------------------------------------------
# paths that leave the session folder are refused before anything is read
# --------------------------------------------------------------------------------------
def _outside(tmp_path) -> Path:
    out = tmp_path / "outside"
    out.mkdir(exist_ok=True)
    (out / "secret.tif").write_bytes(b"not yours")
    (out / "secret.csv").write_text("image,target_id,u,v,sigma_px\n")
    return out


def _link(name, target_of):
    def setup(folder, tmp_path):
        p = folder / name
        if p.exists() or p.is_symlink():
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        p.symlink_to(target_of(folder, _outside(tmp_path)))
    return setup


PATHS = [
    # (id, template, manifest change, setup(folder, tmp_path), file named, message)
    ("glob_dotdot", "marks", _set(("images",), "images/../../outside/*.tif"), None, "session.json",
     r"images path 'images/\.\./\.\./outside/\*\.tif' leaves the session folder"),
    ("glob_absolute", "marks", _set(("images",), "/tmp/*.tif"), None, "session.json",
     r"images path '/tmp/\*\.tif' must be relative to the session folder"),
    ("list_backslash", "marks", _set(("images",), [{"file": "..\\outside\\secret.tif"}]), None, "session.json",
     r"images\[0\] path '\.\./outside/secret\.tif' leaves the session folder"),
    ("list_drive", "marks", _set(("images",), [{"file": "C:/photos/a.tif"}]), None, "session.json",
     r"images\[0\] path 'C:/photos/a\.tif' must be relative"),
    ("list_nul", "marks", _set(("images",), [{"file": "images/a\x00.tif"}]), None, "session.json",
     r"'images/a\\x00\.tif' is not a file of the session: .* \(at /images/0/file\)"),
    ("targets_too_long", "obs", _set(("field", "targets"), "t" * 5000 + ".csv"), None, "session.json",
     r"'t{60}'\.\.\. \(5004 characters\) is not a file of the session: .*1024.* \(at /field/targets\)"),
    ("component_too_long", "obs", _set(("field", "targets"), "t" * 500 + ".csv"), None, "session.json",
     r"field\.targets path 't+\.csv' cannot be used: File name too long"),
    ("images_folder_link", "marks", _set(("images",), "images/*.tif"),
     _link("images", lambda f, out: out), "session.json",
     r"images path 'images/\*\.tif' leads outside the session folder \(link\?\)"),
    ("image_file_link_in_glob", "marks", _set(("images",), "images/*.tif"),
     _link("images/zz.tif", lambda f, out: out / "secret.tif"), "session.json",
     r"image path 'images/zz\.tif' leads outside the session folder \(link\?\)"),
    ("listed_image_link", "marks", None, _link("images/i00.tif", lambda f, out: out / "secret.tif"),
     "session.json", r"images\[0\] path 'images/i00\.tif' leads outside the session folder \(link\?\)"),
    ("targets_link_loop", "obs", None, _link("targets.csv", lambda f, out: f / "targets.csv"), "session.json",
     r"field\.targets path 'targets\.csv' (cannot be used|leads outside)"),
    ("observations_link", "obs", None, _link("observations.csv", lambda f, out: out / "secret.csv"),
     "session.json", r"observations\.csv path 'observations\.csv' leads outside the session folder"),
    ("marks_link", "marks", None, _link("marks.csv", lambda f, out: out / "secret.csv"), "session.json",
     r"marks\.csv path 'marks\.csv' leads outside the session folder"),
    ("frames_file_dotdot", "gonio", _set(("frames",), "../frames.csv"), None, "session.json",
     r"frames path '\.\./frames\.csv' leaves the session folder"),
]


@pytest.mark.parametrize("kind, change, setup, file, match", [c[1:] for c in PATHS], ids=[c[0] for c in PATHS])
def test_paths_that_leave_the_session_folder_are_refused(templates, tmp_path, kind, change, setup, file, match):
    folder = copy(templates, kind, tmp_path / "s")
    if change is not None:
        patch_manifest(folder, change)
    if setup is not None:
        setup(folder, tmp_path)
    refused(folder, match, file)


@pytest.mark.parametrize("row, match", [
    ("../outside/secret.tif,x,5", r"frame path '\.\./outside/secret\.tif' leaves the session folder"),
    ("/etc/passwd,x,5", r"frame path '/etc/passwd' must be relative to the session folder"),
    ("other/link.tif,x,5", r"frame path 'other/link\.tif' leads outside the session folder \(link\?\)"),
])
def test_frames_that_leave_the_session_folder_are_refused_naming_the_line(templates, tmp_path, row, match):
    folder = copy(templates, "gonio", tmp_path / "s")
    (folder / "other").mkdir()
    (folder / "other" / "link.tif").symlink_to(_outside(tmp_path) / "secret.tif")
    with open(folder / "frames.csv", "a") as fh:
        fh.write(row + "\n")
    refused(folder, match, "frames.csv:12")


# --------------------------------------------------------------------------------------
# the tables: missing columns, duplicate ids, NaN / infinite / non-numeric values, empty files
# --------------------------------------------------------------------------------------
def _edit_line(k, edit):
    def change(text):
        lines = text.splitlines()
        lines[k] = edit(lines[k])
        return "\n".join(lines) + "\n"
    return change


def _field(j, value):
    return lambda line: ",".join(value if i == j else c for i, c in enumerate(line.split(",")))


def _append_copy(k):
    return lambda text: text + text.splitlines()[k] + "\n"


def _with_normals(k, normal):
    """targets.csv with columns nx,ny,nz (every target facing -Y), line ``k``'s set to ``normal``."""
    def change(text):
        lines = text.splitlines()
        lines = [lines[0] + ",nx,ny,nz"] + [r + ",0,-1,0" for r in lines[1:]]
        lines[k] = ",".join(lines[k].split(",")[:-3] + normal.split(","))
        return "\n".join(lines) + "\n"
    return change


TABLES = [
    # (id, template, file, change(text) -> text, named as, message)
    ("normals_not_unit", "obs", "targets.csv", _with_normals(3, "0,-1.5,0"), "targets.csv:4",
     r"the normal nx,ny,nz must be a unit vector, got \[0\.0, -1\.5, 0\.0\] of length 1\.5"),
    ("normals_partial", "obs", "targets.csv", _with_normals(2, "0,,0"), "targets.csv:3",
     r"nx, ny, nz must be given together"),
    ("normals_text", "obs", "targets.csv", _with_normals(5, "0,south,0"), "targets.csv:6",
     r"'ny' is not a number: 'south'"),
    ("normals_nan", "obs", "targets.csv", _with_normals(5, "nan,0,1"), "targets.csv:6", r"'nx' is not finite: 'nan'"),
    ("normals_no_nz", "obs", "targets.csv", lambda t: _with_normals(1, "0,-1,0")(t).replace(",nz\n", ",n\n", 1),
     "targets.csv", r"the normal columns nx,ny,nz come together: nx,ny without nz"),
    ("targets_zero_bytes", "obs", "targets.csv", lambda t: "", "targets.csv", r"empty file \(expected a header line"),
    ("targets_no_X", "obs", "targets.csv", _edit_line(0, lambda h: h.replace(",X,", ",x,")), "targets.csv",
     r"missing column\(s\) \['X'\]"),
    ("targets_duplicate_code", "obs", "targets.csv",
     lambda t: _edit_line(2, _field(5, "3"))(_edit_line(1, _field(5, "3"))(t)), "targets.csv:3",
     r"code 3 already used on line 2"),
    ("targets_negative_sigma", "obs", "targets.csv", _edit_line(4, _field(4, "-1")), "targets.csv:5",
     r"sigma_mm must be positive, got -1\.0"),
    ("targets_sigma_text", "obs", "targets.csv", _edit_line(4, _field(4, "five")), "targets.csv:5",
     r"'sigma_mm' is not a number: 'five'"),
    ("targets_extra_field", "obs", "targets.csv", _edit_line(4, lambda r: r + ",9"), "targets.csv:5",
     r"row has 7 fields, the header has 6"),
    ("obs_zero_bytes", "obs", "observations.csv", lambda t: "", "observations.csv", r"empty file"),
    ("obs_header_only", "obs", "observations.csv", lambda t: t.splitlines()[0] + "\n", "observations.csv",
     r"no data rows"),
    ("obs_no_image_column", "obs", "observations.csv", _edit_line(0, lambda h: h.replace("image,", "img,")),
     "observations.csv", r"missing column\(s\) \['image'\]"),
    ("obs_duplicate", "obs", "observations.csv", _append_copy(7), "observations.csv:",
     r":\d+: target 'T\d+' observed twice in 'images/i00\.tif' \(first on line 8\)"),
    ("obs_nan", "obs", "observations.csv", _edit_line(5, _field(2, "nan")), "observations.csv:6",
     r"'u' is not finite: 'nan'"),
    ("obs_inf", "obs", "observations.csv", _edit_line(5, _field(3, "-Infinity")), "observations.csv:6",
     r"'v' is not finite: '-Infinity'"),
    ("obs_huge", "obs", "observations.csv", _edit_line(5, _field(3, "1e999")), "observations.csv:6",
     r"'v' is not finite: '1e999'"),
    ("obs_text", "obs", "observations.csv", _edit_line(5, _field(2, "12,5")), "observations.csv:6",
     r"row has 6 fields, the header has 5"),
    ("obs_comma_decimal", "obs", "observations.csv", _edit_line(5, _field(2, '"12,5"')), "observations.csv:6",
     r"'u' is not a number: '12,5'"),
    ("obs_outside_image", "obs", "observations.csv", _edit_line(5, _field(2, "3000.2")), "observations.csv:6",
     r"point \(3000\.2, [\d.]+\) px is outside the 3000 x 2000 px image"),
    ("obs_sigma_zero", "obs", "observations.csv", _edit_line(5, _field(4, "0")), "observations.csv:6",
     r"sigma_px must be positive, got 0\.0"),
    ("obs_unknown_target", "obs", "observations.csv", _edit_line(5, _field(1, "NO/PE")), "observations.csv:6",
     r"target id 'NO/PE'"),           # an unlisted id is an unsurveyed target, but it must be a valid id
    ("marks_zero_bytes", "marks", "marks.csv", lambda t: "", "marks.csv", r"empty file"),
    ("marks_no_v", "marks", "marks.csv", lambda t: "image,target_id,u\n", "marks.csv", r"missing column\(s\) \['v'\]"),
    ("marks_duplicate", "marks", "marks.csv", _append_copy(1), "marks.csv:",
     r":\d+: target 'T\d+' marked twice in 'images/i00\.tif' \(first on line 2\)"),
    ("marks_nan", "marks", "marks.csv", _edit_line(3, _field(3, "NaN")), "marks.csv:4", r"'v' is not finite: 'NaN'"),
    ("marks_text", "marks", "marks.csv", _edit_line(3, _field(2, "left")), "marks.csv:4",
     r"'u' is not a number: 'left'"),
    ("marks_unknown_image", "marks", "marks.csv", lambda t: t + "images/zz.tif,T001,1,2\n", "marks.csv:",
     r":\d+: image 'images/zz\.tif' is not one of the session's images"),
    ("frames_zero_bytes", "gonio", "frames.csv", lambda t: "", "frames.csv", r"empty file \(0 bytes\)"),
    ("frames_no_axis", "gonio", "frames.csv", _edit_line(0, lambda h: "file,angle_deg"), "frames.csv",
     r"header must be 'file,axis,angle_deg', got 'file,angle_deg'"),
    ("frames_duplicate", "gonio", "frames.csv", _append_copy(2), "frames.csv",
     r"line 12: frame 'images/x-10\.tif' is listed twice \(first on line 3\)"),
    ("frames_fields", "gonio", "frames.csv", _edit_line(4, lambda r: r + ",extra"), "frames.csv",
     r"line 5: expected 3 fields"),
    ("frames_binary", "gonio", "frames.csv", lambda t: "file,axis,angle_deg\n\udcff\udcfe", "frames.csv",
     r"cannot parse as CSV"),
]


@pytest.mark.parametrize("kind, file, change, named, match", [c[1:] for c in TABLES], ids=[c[0] for c in TABLES])
def test_table_errors_name_the_file_and_row(templates, tmp_path, kind, file, change, named, match):
    folder = copy(templates, kind, tmp_path / "s")
    p = folder / file
    p.write_bytes(change(p.read_text()).encode("utf-8", "surrogateescape"))
    refused(folder, match, named)


def test_frames_rows_with_bad_values_are_kept_with_their_line_for_the_report(templates, tmp_path):
    """A bad angle or axis does not stop a goniometer session: the row is reported and skipped
    by the solver (tests/test_goniometer.py); prepare keeps it with a problem naming the line."""
    folder = copy(templates, "gonio", tmp_path / "s")
    p = folder / "frames.csv"
    text = _edit_line(3, _field(2, "nan"))(_edit_line(5, _field(1, "z"))(p.read_text()))
    p.write_text(text)
    prepared = pipeline.prepare(folder)
    problems = [x for x in prepared.frames["problem"].to_pylist() if x]
    assert problems == ["frames.csv line 4: angle_deg 'nan' is not a finite angle within +-90 deg",
                        "frames.csv line 6: axis 'z' is not 'x' or 'y'"]


def test_a_frame_name_with_a_line_break_stays_on_one_line_in_the_message(tmp_path):
    """Found by reading: read_frames_csv(strict=True) printed the raw file name."""
    from fieldcal.session.frames import read_frames_csv

    p = tmp_path / "frames.csv"
    p.write_text('file,axis,angle_deg\n"images/a\nb.tif",z,1\n')
    with pytest.raises(InputError, match=r"\(images/a\\nb\.tif\): axis 'z' is not 'x' or 'y'") as info:
        read_frames_csv(p)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(p))


# --------------------------------------------------------------------------------------
# fieldcal run: exit status, one line on stderr, nothing in the lake
# --------------------------------------------------------------------------------------
def run_cli(prefect_server, folder, lake, tmp_path):
    env = dict(os.environ, PREFECT_API_URL=prefect_server, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               FIELDCAL_HASH_CACHE=str(tmp_path / "hashes.sqlite"), PYTHONPATH=str(ROOT))
    env.pop("FIELDCAL_LAKE", None)
    return subprocess.run([FIELDCAL, "run", str(folder), "--lake", str(lake)], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)


CLI = [
    ("schema", "obs", lambda f, tmp: patch_manifest(f, _set(("sensor", "height_px"), 0)), 2,
     r"session\.json: 0 is less than the minimum of 1 \(at /sensor/height_px\)"),
    ("geometry", None, lambda f, tmp: write_obs_session(f, wall(), SAME_DIRECTION), 1,
     r"the data cannot determine the principal distance: .*add images from other positions"),
]


@pytest.mark.slow
@pytest.mark.parametrize("kind, make, status, match", [c[1:] for c in CLI], ids=[c[0] for c in CLI])
def test_fieldcal_run_exits_non_zero_with_one_line_and_leaves_the_lake_empty(
        prefect_server, templates, tmp_path, kind, make, status, match):
    folder = copy(templates, kind, tmp_path / "s") if kind else tmp_path / "s"
    make(folder, tmp_path)
    lake = tmp_path / "lake"
    proc = run_cli(prefect_server, folder, lake, tmp_path)
    assert proc.returncode == status, proc.stderr
    assert proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert line.startswith("fieldcal run: ")
    assert re.search(match, line), line
    if status == 2:
        assert str(folder) in line                   # the file is named with its full path
    assert Lake(str(lake)).catalog().num_rows == 0
    assert not (lake / "calibrations").exists() and not (lake / "catalog").exists()
    np.testing.assert_equal(sorted(p.name for p in lake.glob("*")) if lake.exists() else [], [])
