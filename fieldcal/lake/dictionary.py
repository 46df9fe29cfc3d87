"""The lake's data dictionary: ``LAKE/README.md``, written at the first commit and kept current.

:func:`data_dictionary` makes the text from the schemas (every table, every column with its
type and unit from the schema's documentation), so it cannot drift from what the code
writes: a commit rewrites ``README.md`` whenever its text differs.
"""

from __future__ import annotations

import pyarrow as pa

from fieldcal.contract.schemas import arrow_schema
from fieldcal.lake.tables import PARTITIONS, TABLES, goniometer_spot_schema, table_schema

__all__ = ["data_dictionary", "column_docs", "HISTORY_DOCS"]

_TABLE_DOCS = {
    "catalog": "One row per committed version: the commit point. A version exists exactly when "
               "its row is here. Camera parameters of CONTRACT section 2 with their sigmas.",
    "residuals": "Image-space residuals of every version, one row per image measurement. "
                 "Rows of a version whose catalog row is absent belong to a commit that failed "
                 "or is in progress: join with the catalog (as fieldcal's views do).",
    "observations_field": "Targets measured in each field image before identification "
                          "(schemas/measurements.arrow.json): the cache that lets a rerun skip "
                          "the pixels. A row with row = -1 marks an image measured with no result.",
    "observations_goniometer": "The spot measured in each goniometer frame: the same cache for "
                               "the goniometer method. row = -1 as above.",
    "rigs": "One row per version of a rig (CONTRACT section 3, Rig sessions): its heads' calibration "
            "versions (each a row of `catalog`) and the rig document (relative orientations, sigmas, "
            "covariance) at `document_path`. The row is written first; the heads' catalog rows, in one "
            "transaction, are the rig version's commit point: a row is a committed rig version only when "
            "every version in `head_versions` is in `catalog` (keep only those: `WHERE NOT EXISTS (SELECT 1 "
            "FROM UNNEST(head_versions) h(v) WHERE v NOT IN (SELECT version FROM catalog))`).",
    "comparisons": "The change test of a version against the previous calibration of its camera "
                   "(fieldcal.lake.order), computed at the commit (and by `fieldcal lake fill`), read by "
                   "history --fleet and the dashboard; keyed by the pair, so a backfill adds the new "
                   "pairs and readers pick the pair of the current order. Derived: may be deleted "
                   "(`fieldcal lake fill` computes it again).",
    "assessments": "The acceptance of each version against the certificate's criteria (without the "
                   "change criterion, which comes from `comparisons`), and its radial distortion at "
                   "fractions of the sensor's half diagonal with sigmas; computed at the commit, read "
                   "by the dashboard. Derived: may be deleted.",
}

_KEY_DOCS = {
    "camera_id": "camera identifier (session.json camera_id)",
    "session_id": "calibration session identifier",
    "version": "version id (catalog.version)",
    "image": "image (field) or frame (goniometer) path relative to the session folder",
    "key": "cache key: SHA-256 (hex) of the image's content and the measuring settings",
    "image_sha256": "SHA-256 (hex) of the image file's bytes, when known",
    "measure_settings": "the session's measuring settings (method, sensor, polarity, coded targets) "
                        "as canonical JSON, when known",
    "row": "position of the row in the image's measurement table; -1: measured, nothing found",
    "version_a": "the earlier version compared",
    "version_b": "the later version compared",
    "settings": "what the row was computed with (the test's definition and grid; the acceptance "
                "thresholds) as canonical JSON",
    "computed": "when the row was computed [UTC]",
    "result": "the figures as a JSON object (comparisons: max_um, p_value, the tests with their "
              "Holm-adjusted p-values ...; the verdict at any alpha and tolerance is derived from them)",
    "radial": "assessments: the radial distortion at 25/50/75/100 % of the sensor's half diagonal as JSON "
              "(r_mm, dr_um, sigma_um: its 1-sigma from the covariance) [mm, um]",
    "verdict": "PASS or FAIL of the acceptance criteria other than the change since the previous "
               "calibration",
}


HISTORY_DOCS = {
    "delta_<name>": "`history --camera`: the change of a parameter since the camera's first row of the "
                    "history [the parameter's unit]",
    "previous_version": "`history --fleet`: the camera's calibration before its latest (the latest version of "
                        "the session acquired before; ties by commit order), compared with it",
    "previous_method": "`history --fleet`: the method of previous_version",
    "previous_acquired": "`history --fleet`: when the session of previous_version was acquired [UTC]",
    "region": "`history --fleet`: where the change was tested: sensor (the whole grid) or axes (the scanned "
              "axes of a goniometer calibration, at its measured spots)",
    "max_change_px": "`history --fleet`: largest change of where a ray lands, where tested [px]",
    "max_change_um": "`history --fleet`: the same in the image plane [um]",
    "rms_change_px": "`history --fleet`: RMS of the change where tested [px]",
    "rms_change_um": "`history --fleet`: the same in the image plane [um]",
    "chi2": "`history --fleet`: chi-square of the map test (the correction field where both observe)",
    "dof": "`history --fleet`: its degrees of freedom",
    "p_value": "`history --fleet`: the family's p-value (smallest Holm-adjusted p-value of the tests of f, "
               "the principal point, the edge distortion and the map)",
    "changed": "`history --fleet`: the quantities that changed significantly at --alpha (f, principal_point, "
               "edge_distortion, map), comma-separated; none: no quantity did; empty: not compared",
    "significant": "`history --fleet`: p_value < alpha (or a change outside what the uncertainties explain)",
    "exceeds_tolerance": "`history --fleet`: max_change_um > tolerance_um",
    "flagged": "`history --fleet`: significant and exceeds_tolerance: the camera moved",
    "tolerance_um": "`history --fleet`: the tolerance used [um]",
    "verdict": "`history --fleet`: the change test in one line (or why there is none)",
}
"""The columns the ``history`` command adds to the catalog's (``--camera`` and ``--fleet``)."""


def column_docs(name: str) -> dict[str, str]:
    """``{column: description with unit}`` of a table, from the schemas' documentation."""
    docs = dict(_KEY_DOCS)
    sources = {"catalog": arrow_schema("catalog"), "residuals": arrow_schema("residuals"),
               "observations_field": arrow_schema("measurements"),
               "observations_goniometer": goniometer_spot_schema()}
    src = sources.get(name)
    if src is not None:
        for f in src:
            doc = (f.metadata or {}).get(b"doc") or (f.metadata or {}).get(b"description")
            if doc:
                docs[f.name] = doc.decode()
    return {f.name: docs.get(f.name, "") for f in table_schema(name)}


def _type(t: pa.DataType) -> str:
    return str(t).replace("timestamp[us, tz=UTC]", "timestamp (UTC, us)")


_READING = """\
## Reading the lake without fieldcal

Every table is a Delta Lake table (a folder with `_delta_log/` and Parquet files). Read the
*table*, not the Parquet files: files of failed commits and of old snapshots may lie beside
the live ones. The documents (`calibrations/C/S/V.json`) and the Zarr v3 groups
(`calibrations/C/S/V.zarr`) are named by the catalog's `document_path` and `zarr_path`.

Only versions in `catalog` exist. Residuals: `residuals SEMI JOIN catalog USING (version)`.

**Python, pyarrow** (through the `deltalake` package)

```python
from deltalake import DeltaTable
catalog = DeltaTable("LAKE/catalog").to_pyarrow_table()
res = DeltaTable("LAKE/residuals").to_pyarrow_dataset()       # lazy, partitioned by camera_id
old = DeltaTable("LAKE/catalog"); old.load_as_version("2026-11-01T00:00:00Z")  # time travel
```

**DuckDB** (the `delta` extension, or through Arrow where extensions cannot be installed)

```sql
SELECT camera_id, version, f_mm, sigma_f_mm FROM delta_scan('LAKE/catalog') ORDER BY committed;
```
```python
import duckdb; from deltalake import DeltaTable
con = duckdb.connect(); con.register("catalog", DeltaTable("LAKE/catalog").to_pyarrow_dataset())
```

**Polars**

```python
import polars as pl
cat = pl.read_delta("LAKE/catalog")
res = pl.scan_delta("LAKE/residuals").filter(pl.col("camera_id") == "cam-1").collect()
```

**Spark** (delta-spark)

```python
spark.read.format("delta").load("LAKE/catalog").createOrReplaceTempView("catalog")
spark.read.format("delta").option("timestampAsOf", "2026-11-01").load("LAKE/catalog")
```

**fieldcal**: `fieldcal history --sql "SELECT ..." --lake LAKE` (read-only views of every
table; `--as-of TIME` for the lake as it was), `fieldcal lake log` (who committed what),
`fieldcal lake check` (damaged objects).

On S3 pass the credentials and endpoint as storage options (`AWS_ENDPOINT_URL`,
`AWS_ACCESS_KEY_ID`, ...); writers need conditional PUTs (`conditional_put=etag`).
"""


_RESIDUALS = """\
## Residuals: what the rows hold

- **Sign and direction.** `du_px, dv_px` are measured minus model, in pixels (u right, v down).
  fieldcal's camera model (`fieldcal-brown/1`, CONTRACT section 2) *corrects* a measured
  image point to the ideal one: `ideal = measured + correction(measured)`. OpenCV, COLMAP and
  Metashape go the other way (they *distort* an ideal point), so their coefficients are not
  fieldcal's: `fieldcal export` fits them.
- **Field rows**: one per image point of a target; both components are set.
- **Goniometer rows**: one per angle and sweep (`axis`, `angle_deg`; `image` null: the mean of
  that angle's frames). The method models only the coordinate along the swept axis, so the
  other component is NaN: `du_px` for the x sweep, `dv_px` for the y sweep. An RMS over both
  components (`sqrt(avg(du_px*du_px + dv_px*dv_px))`) is then NaN; take the component of the row's
  sweep:

  ```sql
  SELECT version, axis, sqrt(avg(power(CASE axis WHEN 'x' THEN du_px ELSE dv_px END, 2))) AS rms_px
  FROM residuals WHERE used AND axis IS NOT NULL GROUP BY version, axis;
  ```

  A frame left out is a row with `used` false, NaN positions and `reason` `FLAG: why`, with
  the flags of `observations_goniometer.flag`: `ok` (measured), `missing` (no spot found),
  `saturated` (the spot's peak at full scale), `truncated` (the spot touches the frame's
  border), `double` (two spots), `unreadable` (the file is missing, corrupt or not the
  sensor's size); while averaging the frames of an angle: `bad_row` (frames.csv's row cannot
  be used), `unmeasured` (no measurement for the frame), `inconsistent` (the frame's spot
  disagrees with the other frames of its angle).
"""


def _history_section() -> list[str]:
    out = ["## What `fieldcal history` shows", "",
           "Plain `history`: every camera's latest calibration, catalog columns. `--camera ID`: the "
           "latest version of each session (`--all-versions`: every one), catalog columns and, per "
           "parameter asked for, `delta_<name>`. `--fleet`: the columns below. As text, a default set "
           "that fits a terminal (`--columns A,B` names others, `--wide` shows all); CSV and JSON carry "
           "every column.", "", "| column | description [unit] |", "| --- | --- |"]
    out += [f"| `{k}` | {v.replace('|', chr(92) + '|')} |" for k, v in HISTORY_DOCS.items()]
    return out + [""]


def data_dictionary() -> str:
    """The text of ``LAKE/README.md``."""
    out = ["# fieldcal lake", "",
           "Written by fieldcal at every commit whose dictionary changed: do not edit.",
           "Conventions and units: CONTRACT.md (pixel (u, v) right/down from the centre of the",
           "top-left pixel; image plane (x, y) in mm, y up; world in metres).", "",
           "## Layout", "", "```",
           "catalog/                    Delta: one row per committed version (the commit point)",
           "residuals/                  Delta: residuals of every version, partitioned by camera_id",
           "observations_field/         Delta: targets measured per field image (cache), by camera_id",
           "observations_goniometer/    Delta: the spot of each goniometer frame (cache), by camera_id",
           "comparisons/                Delta: the change test of two versions (derived)",
           "assessments/                Delta: the acceptance of each version (derived)",
           "rigs/                       Delta: one row per committed rig version (its heads' versions)",
           "rigs/R/S/V.json             the rig document of rig version V (fieldcal.rig/1)",
           "calibrations/C/S/V.json     the calibration document of version V (CONTRACT section 4)",
           "calibrations/C/S/V.zarr     Zarr v3 group: parameters, sigma, covariance, correlation,",
           "                            exterior/*, correction_field, grid_u_px, grid_v_px",
           "quarantine/                 damaged files moved aside by fieldcal (never read; see",
           "                            `fieldcal lake repair`)",
           "```", "", _READING, _RESIDUALS, "## Tables", ""]
    for name in TABLES:
        part = ", ".join(PARTITIONS[name]) or "not partitioned"
        out += [f"### {name}", "", _TABLE_DOCS[name], "", f"Partitioned by: {part}.", "",
                "| column | type | null | description [unit] |", "| --- | --- | --- | --- |"]
        docs = column_docs(name)
        for f in table_schema(name):
            text = docs.get(f.name, "").replace("|", "\\|")
            out.append(f"| `{f.name}` | {_type(f.type)} | {'yes' if f.nullable else 'no'} | {text} |")
        out.append("")
    out += _history_section()
    return "\n".join(out) + "\n"
