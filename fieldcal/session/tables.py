"""The CSV tables of a field session (docs/conventions.md section 3): targets.csv, observations.csv, marks.csv.

Each table is read once, in one pass, into Arrow string columns with the line number of
every row, and then checked column by column (vectorised): required columns, names as the
schema defines them (:mod:`fieldcal.contract.names`), unique ids, finite numbers, positive
sigmas, known targets and images. Every refusal is an :class:`InputError` of one line that
names the file and the line (``targets.csv:325: duplicate target id 'W0005' (first on line
6)``).

Reading
-------
- Cells are text; surrounding ASCII white space (``" \\t\\r\\n\\v\\f"``) is trimmed.
  A row whose cells are all empty is skipped; a row with fewer cells than the header is
  padded with empty cells; a row with more is refused. Columns beyond the contract's are
  ignored. A UTF-8 byte-order mark is skipped.
- Numbers are decimal (``12``, ``-0.5``, ``1.5e-3``); ``nan``, ``inf`` and values beyond
  the float range are refused as not finite, anything else (``0x10``, ``1_000``, ``12,5``)
  as not a number.
- Two tokenisers give the same cells and line numbers: a file without a double quote (a
  quote is what lets a cell hold a comma or a line break) is split by ``pyarrow.csv`` in
  C++, where every line is a row; any other file by Python's :mod:`csv` module.
  ``tests/session/test_fuzz.py`` checks that they agree.

Limits
------
Files larger than any real session needs are refused before they are read (``stat``),
and the row count is bounded while reading, so a hostile or mistaken file costs neither
minutes nor gigabytes (a 10-million-row targets.csv: refused at once):

==================  ============  ==============
file                bytes         rows
==================  ============  ==============
targets.csv         16 MiB        100 000 targets (the paper's field: 2 000)
observations.csv    128 MiB       2 000 000 points (the paper: 72 images x ~2 000)
marks.csv           16 MiB        100 000 marks
==================  ============  ==============

:data:`MAX_IMAGES` bounds the images of a session (10 000; the paper: 72), session.json
and frames.csv are bounded by :data:`MAX_BYTES` too (read elsewhere).
"""

from __future__ import annotations

import codecs
import csv
import io
import os
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from fieldcal.contract.names import check_name, first_invalid, normal_file_name
from fieldcal.contract.schemas import shown
from fieldcal.errors import InputError
from fieldcal.model.camera import Sensor
from fieldcal.session.data import (
    DEFAULT_TARGET_SIGMA_MM,
    FieldImage,
    FieldObservations,
    ScaleBars,
    TargetField,
    normal_problem,
)

__all__ = ["MAX_BYTES", "MAX_ROWS", "MAX_IMAGES", "CsvTable", "check_size", "read_csv_table",
           "read_targets_csv", "read_observations_csv", "read_marks_csv", "read_scale_bars_csv"]

MiB = 1 << 20
MAX_BYTES = {"session.json": 16 * MiB, "targets.csv": 16 * MiB, "observations.csv": 128 * MiB,
             "marks.csv": 16 * MiB, "frames.csv": 16 * MiB, "scale_bars.csv": 1 * MiB}
"""Largest file accepted, per kind of file [bytes]."""
MAX_ROWS = {"scale_bars.csv": 10_000, "targets.csv": 100_000, "observations.csv": 2_000_000, "marks.csv": 100_000}
"""Most data rows accepted, per table."""
MAX_IMAGES = 10_000
"""Most images (or goniometer frames) in one session."""

WHITESPACE = " \t\r\n\x0b\x0c"
"""The white space trimmed around a cell (ASCII only; anything else stays and is checked)."""
_NUMBER = r"^[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?$"
_NOT_FINITE = r"(?i)^[+-]?(nan|inf|infinity)$"
_CODE = r"^\+?[0-9]{1,10}$"
MAX_CODE = 2**31 - 1


def check_size(path, kind: str, where: str | None = None) -> int:
    """The size of a file [bytes]; refused if larger than :data:`MAX_BYTES` of its kind."""
    try:
        size = os.stat(path).st_size
    except FileNotFoundError:
        raise InputError("file not found", where or str(path)) from None
    except OSError as err:
        raise InputError(f"cannot read: {err.strerror or err}", where or str(path)) from None
    if size > MAX_BYTES[kind]:
        raise InputError(f"file of {size / MiB:.1f} MiB; a {kind} is at most {MAX_BYTES[kind] // MiB} MiB "
                         f"(fieldcal's limit: more than any real session needs)", where or str(path))
    return size


# ---------------------------------------------------------------------------- reading
@dataclass
class CsvTable:
    """A CSV table as read: trimmed text columns and the line number of every row.

    Attributes
    ----------
    path : str
    header : list of str
        The header's cells, trimmed.
    columns : dict of str to pyarrow.StringArray
        The required and optional columns present, one value per row (``""`` when empty).
    lines : (n,) ndarray of int64
        The line of the file each row starts on (the header is line 1).
    """

    path: str
    header: list[str]
    columns: dict[str, pa.Array]
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.lines)

    def where(self, row: int) -> str:
        """``path:line`` of a row, for a message."""
        return f"{self.path}:{int(self.lines[row])}"

    def text(self, column: str) -> list[str]:
        """A column as Python strings."""
        return self.columns[column].to_pylist()


def _header(first: list[str], required, optional, where) -> list[str]:
    header = [h.strip(WHITESPACE) for h in first]
    missing = [c for c in required if c not in header]
    if missing:
        cells = ", ".join(shown(h, 40) for h in header[:20]) + (", ..." if len(header) > 20 else "")
        raise InputError(f"missing column(s) {missing}; header is [{cells}]", where)
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise InputError(f"duplicate column(s) {dup} in the header", where)
    return header


def _blank(cells) -> bool:
    return all(not c.strip(WHITESPACE) for c in cells)


def _too_many(n: int, kind: str, where: str):
    return InputError(f"more than {MAX_ROWS[kind]} rows (fieldcal's limit for a {kind}: more than any "
                      f"real session needs)", where)


def _tokenise_python(raw: bytes, width: int, keep: dict[str, int], kind: str, where: str):
    """Python's csv module: (columns as lists of str, first line of each row)."""
    text = raw.decode("utf-8-sig")
    reader = csv.reader(io.StringIO(text, newline=""))
    next(reader)
    cols: list[list[str]] = [[] for _ in keep]
    lines: list[int] = []
    idx = list(keep.values())
    line = reader.line_num + 1
    for rec in reader:
        if len(rec) != width:
            if not rec or _blank(rec):
                line = reader.line_num + 1
                continue
            if len(rec) > width:
                raise InputError(f"row has {len(rec)} fields, the header has {width}", f"{where}:{line}")
            rec = rec + [""] * (width - len(rec))
        if len(lines) >= MAX_ROWS[kind]:
            raise _too_many(len(lines), kind, where)
        for c, i in zip(cols, idx, strict=True):
            c.append(rec[i])
        lines.append(line)
        line = reader.line_num + 1
    return {name: pa.array(c, pa.string()) for name, c in zip(keep, cols, strict=True)}, np.array(lines, np.int64)


def _tokenise_arrow(raw: bytes, width: int, keep: dict[str, int], kind: str, where: str):
    """pyarrow.csv for a file without quotes (every line a row); None when it cannot read it."""
    odd: list[tuple[int, str]] = []

    def invalid(row):
        odd.append((row.number, row.text))
        return "skip"

    names = [f"c{i}" for i in range(width)]
    try:
        table = pacsv.read_csv(
            pa.py_buffer(raw),
            read_options=pacsv.ReadOptions(use_threads=False, skip_rows=1, column_names=names),
            parse_options=pacsv.ParseOptions(quote_char=False, newlines_in_values=False,
                                             ignore_empty_lines=False, invalid_row_handler=invalid),
            convert_options=pacsv.ConvertOptions(column_types={n: pa.string() for n in names},
                                                 strings_can_be_null=False, quoted_strings_can_be_null=False))
    except (pa.ArrowException, UnicodeDecodeError):
        return None                                    # the Python tokeniser names the problem
    if any(n is None for n, _ in odd):
        return None
    all_lines = np.arange(2, 2 + table.num_rows + len(odd), dtype=np.int64)
    lines = np.setdiff1d(all_lines, [n for n, _ in odd], assume_unique=True)
    if len(lines) != table.num_rows:
        return None
    columns = {name: table.column(f"c{i}").combine_chunks() for name, i in keep.items()}
    extra = []
    for number, text in sorted(odd):                   # short, long or blank rows, in line order
        cells = text.split(",")
        if _blank(cells):
            continue
        if len(cells) > width:
            raise InputError(f"row has {len(cells)} fields, the header has {width}", f"{where}:{number}")
        extra.append((number, cells + [""] * (width - len(cells))))
    if extra:
        order = np.argsort(np.concatenate([lines, [n for n, _ in extra]]), kind="stable")
        lines = np.concatenate([lines, [n for n, _ in extra]])[order]
        columns = {name: pa.concat_arrays([columns[name], pa.array([c[i] for _, c in extra], pa.string())]).take(order)
                   for name, i in keep.items()}
    if len(lines) > MAX_ROWS[kind]:
        raise _too_many(len(lines), kind, where)
    return columns, lines


def read_csv_table(path, required: tuple[str, ...], optional: tuple[str, ...] = (), *,
                   kind: str, tokeniser: str = "auto") -> CsvTable:
    """Read a CSV table of the session (module docstring): header, text columns, line numbers.

    Parameters
    ----------
    path : path-like
    required, optional : tuple of str
        Columns that must be present, and columns read when present (others are ignored).
    kind : str
        The kind of file (``"targets.csv"``, ...): its limits (:data:`MAX_BYTES`, :data:`MAX_ROWS`).
    tokeniser : {"auto", "arrow", "python"}
        ``"auto"``: pyarrow for a file without a double quote, else (or when pyarrow cannot
        read it) Python's csv module. ``"arrow"`` and ``"python"`` force one (tests compare
        them); ``"arrow"`` refuses what it cannot split.

    Returns
    -------
    CsvTable
        Blank rows dropped; cells trimmed of ASCII white space; at least one row.

    Raises
    ------
    InputError
        Missing file, too large, not UTF-8, not CSV, missing or repeated columns, a row with
        too many fields, more rows than the limit, no data rows.
    """
    where = str(path)
    size = check_size(path, kind, where)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(size + 1)                 # (read(n) sets n bytes aside first)
        if len(raw) > size:                         # growing while read: a log, not a table
            check_size(path, kind, where)
            raise InputError("changed while it was read", where)
    except FileNotFoundError:
        raise InputError("file not found", where) from None
    except OSError as err:
        raise InputError(f"cannot read: {err.strerror or err}", where) from None
    try:                                            # the header, from the first 64 KiB
        head = codecs.getincrementaldecoder("utf-8-sig")().decode(raw[:1 << 16], final=len(raw) <= 1 << 16)
        first = next(csv.reader(io.StringIO(head, newline="")), None)
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text", where) from None
    except csv.Error as err:
        raise InputError(f"not a valid CSV file ({err})", where) from None
    if first is None:
        raise InputError(f"empty file (expected a header line {','.join(required + optional)})", where)
    header = _header(first, required, optional, where)
    keep = {c: header.index(c) for c in required + optional if c in header}
    got = None
    if tokeniser == "arrow" or (tokeniser == "auto" and b'"' not in raw):
        got = _tokenise_arrow(raw, len(header), keep, kind, where)
    if got is None and tokeniser == "arrow":
        raise InputError("pyarrow cannot split this file (quotes, or a line it does not read)", where)
    if got is None:
        try:
            got = _tokenise_python(raw, len(header), keep, kind, where)
        except UnicodeDecodeError:
            raise InputError("not UTF-8 text", where) from None
        except csv.Error as err:
            raise InputError(f"not a valid CSV file ({err})", where) from None
    columns, lines = got
    columns = {name: pc.utf8_trim(col, WHITESPACE) for name, col in columns.items()}
    if len(lines):
        blank = np.ones(len(lines), bool)
        for col in columns.values():
            blank &= np.asarray(pc.equal(col, "").to_numpy(zero_copy_only=False), bool)
        if blank.any():
            keep_rows = np.flatnonzero(~blank)
            columns = {name: col.take(keep_rows) for name, col in columns.items()}
            lines = lines[keep_rows]
    if not len(lines):
        raise InputError("no data rows", where)
    return CsvTable(where, header, columns, lines)


# ---------------------------------------------------------------------------- checks
def _first(mask) -> int | None:
    hits = np.flatnonzero(mask)
    return int(hits[0]) if len(hits) else None


def _numbers(t: CsvTable, column: str, *, default: float | None = None) -> np.ndarray:
    """A column of finite numbers (``default`` for empty cells, else empty is refused)."""
    col = t.columns.get(column)
    if col is None:
        return np.full(len(t), default, float)
    empty = np.asarray(pc.equal(col, "").to_numpy(zero_copy_only=False), bool)
    if default is None and (k := _first(empty)) is not None:
        raise InputError(f"empty value in column {column!r}", t.where(k))
    good = np.asarray(pc.match_substring_regex(col, _NUMBER).to_numpy(zero_copy_only=False), bool)
    if (k := _first(~good & ~empty)) is not None:
        text = col[k].as_py()
        problem = "is not finite" if pc.match_substring_regex(pa.array([text]), _NOT_FINITE)[0].as_py() \
            else "is not a number"
        raise InputError(f"{column!r} {problem}: {shown(text)}", t.where(k))
    values = np.array(pc.cast(pc.if_else(pa.array(empty), "0", col), pa.float64())
                        .to_numpy(zero_copy_only=False), float)
    if (k := _first(~np.isfinite(values))) is not None:
        raise InputError(f"{column!r} is not finite: {shown(col[k].as_py())}", t.where(k))
    if default is not None:
        values[empty] = default
    return values


PLAUSIBLE = {"sigma_px": (1e-4, 1e3, "px"), "sigma_mm": (1e-3, 1e6, "mm")}
"""Accuracies a measurement can have ``(lowest, highest, unit)``: beyond them a value is a typo
(a weight of 1e24 would be diagnosed as bad geometry instead)."""


def _positive(t: CsvTable, values: np.ndarray, column: str) -> np.ndarray:
    if (k := _first(values <= 0)) is not None:
        raise InputError(f"{column} must be positive, got {values[k]}", t.where(k))
    lo, hi, unit = PLAUSIBLE.get(column, (0.0, np.inf, ""))
    if (k := _first((values < lo) | (values > hi))) is not None:
        raise InputError(f"{column} {values[k]:g} {unit} is not a plausible accuracy ({lo:g} to {hi:g} {unit})",
                         t.where(k))
    return values


def _first_repeat(keys: np.ndarray) -> tuple[int, int] | None:
    """(row, row of its first occurrence) of the first row whose key came before, or None."""
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    repeat = first[inverse] != np.arange(len(keys))
    k = _first(repeat)
    return None if k is None else (k, int(first[inverse[k]]))


def _codes(t: CsvTable) -> np.ndarray:
    out = np.full(len(t), -1, np.int64)
    if "code" not in t.columns:
        return out
    col = t.columns["code"]
    given = np.flatnonzero(np.asarray(pc.not_equal(col, "").to_numpy(zero_copy_only=False), bool))
    good = np.asarray(pc.match_substring_regex(col, _CODE).to_numpy(zero_copy_only=False), bool)[given]
    if good.all():
        out[given] = np.asarray(pc.cast(pc.utf8_ltrim(col.take(given), "+"), pa.int64()), np.int64)
    bad = given[~good | (out[given] > MAX_CODE)]
    if len(bad):
        raise InputError(f"'code' must be an ArUco id (a whole number from 0 to {MAX_CODE}), "
                         f"got {shown(col[int(bad[0])].as_py())}", t.where(int(bad[0])))
    coded = np.flatnonzero(out >= 0)
    if (hit := _first_repeat(out[coded])) is not None:
        k, first = coded[hit[0]], coded[hit[1]]
        raise InputError(f"code {out[k]} already used on line {t.lines[first]}", t.where(k))
    return out


def read_targets_csv(path, *, tokeniser: str = "auto") -> TargetField:
    """``targets.csv``: ``id,X,Y,Z,sigma_mm,code`` -> :class:`TargetField`.

    ``X, Y, Z`` [m], all three empty for an unsurveyed target (NaN); an empty ``sigma_mm`` is
    5 mm; an empty ``code`` a plain target. Ids are
    names of the kind ``label`` (:mod:`fieldcal.contract.names`), unique; codes unique.
    ``tokeniser``: see :func:`read_csv_table`.
    """
    t = read_csv_table(path, ("id", "X", "Y", "Z"), ("sigma_mm", "code") + NORMAL_COLUMNS, kind="targets.csv",
                       tokeniser=tokeniser)
    ids = t.text("id")
    if (k := first_invalid(ids, "label")) is not None:
        if not ids[k]:
            raise InputError("empty target id", t.where(k))
        check_name(ids[k], "label", "target id", t.where(k))
    if len(pc.unique(t.columns["id"])) < len(ids) and (hit := _first_repeat(np.array(ids, dtype=object))):
        k, first = hit
        raise InputError(f"duplicate target id {ids[k]!r} (first on line {t.lines[first]})", t.where(k))
    xyz = np.column_stack([_numbers(t, c, default=np.nan) for c in ("X", "Y", "Z")])
    partial = np.isnan(xyz).any(axis=1) & ~np.isnan(xyz).all(axis=1)
    if (k := _first(partial)) is not None:
        raise InputError("X, Y, Z must all be given (a surveyed target) or all be empty (an "
                         "unsurveyed one)", t.where(k))
    sigma = _positive(t, _numbers(t, "sigma_mm", default=DEFAULT_TARGET_SIGMA_MM), "sigma_mm")
    return TargetField(np.array(ids, dtype=str), xyz, sigma, _codes(t), _normals(t))


NORMAL_COLUMNS = ("nx", "ny", "nz")
"""targets.csv's optional columns of a target's unit normal (docs/conventions.md section 3)."""


def _normals(t: CsvTable) -> np.ndarray | None:
    """The ``nx,ny,nz`` columns: (n, 3) unit normals, NaN rows where empty; None without the columns."""
    present = [c for c in NORMAL_COLUMNS if c in t.columns]
    if not present:
        return None
    if len(present) < 3:
        missing = [c for c in NORMAL_COLUMNS if c not in t.columns]
        raise InputError(f"the normal columns nx,ny,nz come together: {','.join(present)} without "
                         f"{','.join(missing)}", t.path)
    N = np.column_stack([_numbers(t, c, default=np.nan) for c in NORMAL_COLUMNS])
    given = np.isfinite(N)
    if (k := _first(given.any(axis=1) & ~given.all(axis=1))) is not None:
        raise InputError("nx, ny, nz must be given together (all three, or all empty for an unknown normal)",
                         t.where(k))
    for k in np.flatnonzero(given.all(axis=1)):
        if (why := normal_problem(N[k])) is not None:
            raise InputError(f"the normal nx,ny,nz {why}", t.where(int(k)))
    if not given.any():
        return None
    rows = given.all(axis=1)
    N[rows] /= np.linalg.norm(N[rows], axis=1, keepdims=True)
    return N


def _image_index(t: CsvTable, images: list[FieldImage], allow_new: bool, what: str) -> np.ndarray:
    """Row -> index into ``images`` of the ``image`` column (names compared in their normal
    spelling); with ``allow_new``, unknown images are appended in order of first appearance."""
    encoded = t.columns["image"].dictionary_encode()
    rows = np.asarray(encoded.indices.to_numpy(zero_copy_only=False), np.int64)
    names = encoded.dictionary.to_pylist()
    if len(names) + len(images) > MAX_IMAGES and allow_new:
        raise InputError(f"more than {MAX_IMAGES} images (fieldcal's limit for one session)", t.path)
    first_row = np.full(len(names), len(rows))
    np.minimum.at(first_row, rows, np.arange(len(rows)))
    index = {im.file: i for i, im in enumerate(images)}
    mapping = np.empty(len(names), np.int64)
    for j in np.argsort(first_row, kind="stable"):
        where = t.where(first_row[j])
        name = normal_file_name(names[j], "image", where)
        if name not in index:
            if not allow_new:
                raise InputError(f"image {shown(name)} is not one of the session's images", where)
            index[name] = len(images)
            images.append(FieldImage(name, None))
        mapping[j] = index[name]
    return mapping[rows]


def _target_index(t: CsvTable, targets: TargetField, column: str = "target_id") -> np.ndarray:
    """Row -> index into ``targets`` of ``column``; -1 for an id targets.csv does not list."""
    found = pc.index_in(t.columns[column], value_set=pa.array(targets.ids.tolist(), pa.string()))
    return np.asarray(found.fill_null(-1).to_numpy(zero_copy_only=False), np.int64)


def _unlisted(t: CsvTable, tgt: np.ndarray, column: str = "target_id") -> InputError | None:
    """The refusal of the first row whose target id targets.csv does not list (None: all listed)."""
    if (k := _first(tgt < 0)) is None:
        return None
    return InputError(f"{column} {shown(t.columns[column][k].as_py())} is not in targets.csv", t.where(k))


def _image_targets(t: CsvTable, targets: TargetField, images: list[FieldImage], allow_new: bool,
                   verb: str) -> tuple[np.ndarray, np.ndarray]:
    """(image index, target index) per row; an (image, target) pair at most once; every
    target listed in ``targets``."""
    img = _image_index(t, images, allow_new, verb)
    tgt = _target_index(t, targets)
    if (err := _unlisted(t, tgt)) is not None:
        raise err
    _check_pairs(t, targets, images, img, tgt, verb)
    return img, tgt


class _Named:
    """Target ids by index: the listed ones, then the unlisted ones (for messages)."""

    def __init__(self, targets: TargetField, unlisted: list[str]):
        self.ids = np.concatenate([targets.ids, np.asarray(unlisted, dtype=str)]) if unlisted else targets.ids


def _check_pairs(t, targets, images, img, tgt, verb, n_targets=None):
    n = len(targets.ids) if n_targets is None else n_targets
    if (hit := _first_repeat(img * max(n, 1) + tgt)) is not None:
        k, first = hit
        raise InputError(f"target {str(targets.ids[tgt[k]])!r} {verb} twice in {images[img[k]].file!r} "
                         f"(first on line {t.lines[first]})", t.where(k))
    return img, tgt


def read_observations_csv(path, targets: TargetField, images: list[FieldImage], *,
                          default_sigma_px: float, allow_new_images: bool, sensor: Sensor | None = None,
                          tokeniser: str = "auto", unlisted: list[str] | None = None):
    """``observations.csv``: ``image,target_id,u,v,sigma_px`` -> :class:`FieldObservations`.

    ``images`` is extended in place with images the file names (when ``allow_new_images``,
    i.e. the manifest's glob matched no file). A (image, target) pair may appear once; two
    spellings of one image's path (``images/./a.tif``) are the same image. With ``sensor``,
    a point must lie on the image (``[-0.5, W-0.5] x [-0.5, H-0.5]`` px, docs/conventions.md section 1).

    ``unlisted``: None refuses a target id that ``targets`` does not list (the strict
    session); a list receives those ids in order of first appearance, and their points get
    the indices ``len(targets) + position in the list`` (unsurveyed targets, CONTRACT section 3:
    the caller extends the targets with :meth:`TargetField.with_unsurveyed`).
    """
    t = read_csv_table(path, ("image", "target_id", "u", "v"), ("sigma_px",), kind="observations.csv",
                       tokeniser=tokeniser)
    img = _image_index(t, images, allow_new_images, "observed")
    tgt = _target_index(t, targets)
    if unlisted is None:
        if (err := _unlisted(t, tgt)) is not None:
            raise err
    elif (tgt < 0).any():
        rows = np.flatnonzero(tgt < 0)
        names = np.asarray(t.columns["target_id"].take(pa.array(rows)).to_pylist(), dtype=object)
        new, first, inverse = np.unique(names, return_index=True, return_inverse=True)
        order = np.argsort(first, kind="stable")           # ids in order of first appearance
        rank = np.empty(len(new), np.int64)
        rank[order] = np.arange(len(new))
        if (k := first_invalid([str(x) for x in new[order]], "label")) is not None:
            check_name(str(new[order][k]), "label", "target id", t.where(int(rows[first[order][k]])))
        unlisted.extend(str(x) for x in new[order])
        tgt[rows] = len(targets) + rank[inverse.reshape(-1)]
    n_targets = len(targets) + (len(unlisted) if unlisted else 0)
    _check_pairs(t, _Named(targets, unlisted or []), images, img, tgt, "observed", n_targets)
    sigma = _positive(t, _numbers(t, "sigma_px", default=default_sigma_px), "sigma_px")
    u, v = _numbers(t, "u"), _numbers(t, "v")
    if sensor is not None:
        off = ~((u >= -0.5) & (u <= sensor.width_px - 0.5) & (v >= -0.5) & (v <= sensor.height_px - 0.5))
        if (k := _first(off)) is not None:
            raise InputError(f"point ({u[k]:g}, {v[k]:g}) px is outside the {sensor.width_px} x "
                             f"{sensor.height_px} px image", t.where(k))
    return FieldObservations(img, tgt, np.column_stack([u, v]), sigma)


MARKS_COLUMNS = ("image", "target_id", "u", "v")


def read_marks_csv(path, targets: TargetField, images: list[FieldImage], *, table: CsvTable | None = None
                   ) -> dict[int, tuple]:
    """``marks.csv``: ``image,target_id,u,v`` -> ``{image index: (target indices, uv (n,2))}``.

    ``table``: the file as :func:`read_csv_table` read it already (``path`` is not read again)."""
    t = table if table is not None else read_csv_table(path, MARKS_COLUMNS, kind="marks.csv")
    img, tgt = _image_targets(t, targets, images, False, "marked")
    uv = np.column_stack([_numbers(t, "u"), _numbers(t, "v")])
    return {int(i): (tgt[img == i], uv[img == i]) for i in dict.fromkeys(img.tolist())}


def read_scale_bars_csv(path, targets: TargetField) -> ScaleBars:
    """``scale_bars.csv``: ``from_id,to_id,length_mm,sigma_mm`` -> :class:`ScaleBars`.

    Both ids must be targets of the session (surveyed or not; CONTRACT section 3), distinct;
    ``length_mm`` and ``sigma_mm`` positive.
    """
    t = read_csv_table(path, ("from_id", "to_id", "length_mm", "sigma_mm"), kind="scale_bars.csv")
    a, b = _target_index(t, targets, "from_id"), _target_index(t, targets, "to_id")
    for idx, column in ((a, "from_id"), (b, "to_id")):
        if (k := _first(idx < 0)) is not None:
            raise InputError(f"{column} {shown(t.columns[column][k].as_py())} is not a target of the "
                             "session (targets.csv or observations.csv)", t.where(k))
    if (k := _first(a == b)) is not None:
        raise InputError(f"a scale bar from target {str(targets.ids[a[k]])!r} to itself", t.where(k))
    length = _positive(t, _numbers(t, "length_mm"), "length_mm")
    sigma = _positive(t, _numbers(t, "sigma_mm"), "sigma_mm")
    return ScaleBars(a, b, length, sigma)
